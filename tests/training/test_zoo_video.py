"""A zoo dataset converted to AV1 video by lerobot's own conversion: the same frames within the
codec's loss, the camera stats and the parts list kept, and a fraction of the bytes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from training.zoo_video import convert


@pytest.mark.slow
def test_the_video_copy_keeps_frames_stats_and_parts_in_fewer_bytes(
    synthetic_tabletop, tmp_path
) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    dst = convert(synthetic_tabletop, tmp_path / "video")
    info = json.loads((dst / "meta" / "info.json").read_text())
    cams = [k for k in info["features"] if k.startswith("observation.images.")]
    assert len(cams) == 2 and all(info["features"][k]["dtype"] == "video" for k in cams)
    stats = json.loads((dst / "meta" / "stats.json").read_text())
    src_stats = json.loads((synthetic_tabletop / "meta" / "stats.json").read_text())
    assert all(stats[k] == src_stats[k] for k in cams)  # lerobot-train reads them
    assert json.loads((dst / "meta" / "zoo_parts.json").read_text()) == {"synthetic": 2}

    src, vid = LeRobotDataset("a", root=synthetic_tabletop), LeRobotDataset("b", root=dst)
    assert len(src) == len(vid) == 60
    for i in (0, 17, 45):  # within a GOP and across the episode boundary
        a, b = src[i], vid[i]
        assert a["episode_index"] == b["episode_index"] and a["frame_index"] == b["frame_index"]
        assert np.array_equal(a["action"], b["action"])
        for k in cams:
            assert np.abs(a[k].numpy() - b[k].numpy()).mean() < 0.03  # AV1's loss, in [0, 1]

    def size(root):
        return sum(p.stat().st_size for p in root.rglob("*") if p.is_file())

    with pytest.raises(SystemExit, match="exists"):
        convert(synthetic_tabletop, dst)
    assert size(dst) < size(synthetic_tabletop)
