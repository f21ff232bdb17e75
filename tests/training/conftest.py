"""A small LeRobotDataset with the tabletop's features, written without a simulator."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest


@pytest.fixture(scope="session")
def synthetic_tabletop(tmp_path_factory) -> Path:
    """Two episodes of 30 frames: smooth moving images on both 96 px cameras (what a video
    codec sees in a rendered scene), an 8-d state, a 7-d action and an instruction the zoo's
    tiny VLA knows."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from training.tabletop_demos import features

    root = tmp_path_factory.mktemp("synthetic") / "ds"
    cams = ["agentview", "wrist"]
    ds = LeRobotDataset.create(
        "local/synthetic", fps=20, features=features(96, tuple(cams)), root=root, use_videos=False
    )
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:96, 0:96]
    for ep in range(2):
        for t in range(30):
            frame = {}
            for c, cam in enumerate(cams):
                cx, cy = 20 + 2 * t + 10 * ep, 40 + 15 * c
                blob = np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / 120.0)
                img = np.stack([blob, 0.5 * blob + 0.2, np.full_like(blob, 0.3)], -1)
                frame[f"observation.images.{cam}"] = (255 * img).astype(np.uint8)
            frame["observation.state"] = rng.normal(size=8).astype(np.float32)
            frame["action"] = rng.normal(size=7).astype(np.float32)
            frame["task"] = "pick up the red cube"
            ds.add_frame(frame)
        ds.save_episode()
    ds.finalize()
    (root / "meta" / "zoo_parts.json").write_text('{"synthetic": 2}\n')
    return root
