"""Held-out demonstration frames for the open-loop reliance measure, read from a local
LeRobotDataset (a benchmark's demonstrations recorded from seeds no member trained on, e.g.
``python -m training.metaworld_demos --root data/zoo/metaworld_heldout --first-episode 200000``).

Each frame carries what observation 3 is read on: its normalized progress through its episode
(``progress`` in [0, 1], and its fifth, 0-4) and, where the task has a gripper, its gripper
phase from the demonstration's own gripper command (the action's ``gripper_dim``: > 0 closes):

- ``open``: the gripper open, before any close in the episode (reaching, approaching);
- ``closed``: the gripper closed (grasping, carrying, pushing with a closed hand);
- ``released``: open again after a close (after the release);
- ``none``: an episode whose gripper never closes (the phases do not apply).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from idr_core.features import ACTION, OBS_STATE, camera_of

from pipeline.errors import ConfigError
from pipeline.reporting.reliance import FIFTHS, PHASES  # noqa: F401  (PHASES: the labels)


@dataclass(frozen=True)
class FrameSet:
    """Frames in the format of ``pipeline.api.diagnose`` and one row of meta per frame."""

    frames: dict[str, Any]  # images {camera: (N, 3, H, W)}, state (N, S), instruction [N]
    meta: pd.DataFrame  # task_id, episode_index, frame_index, progress, fifth, phase
    source: str

    @property
    def n(self) -> int:
        return len(self.meta)


def gripper_phases(closing: np.ndarray) -> list[str]:
    """One episode's phase per frame from its gripper command (True: closing)."""
    if not closing.any():
        return ["none"] * len(closing)
    out, seen_close = [], False
    for c in closing:
        seen_close |= bool(c)
        out.append("closed" if c else ("released" if seen_close else "open"))
    return out


def episode_meta(
    task: str, episode: int, actions: np.ndarray, gripper_dim: int | None
) -> pd.DataFrame:
    """The meta rows of one episode's frames (``actions``: (T, D), the demonstration's)."""
    t = len(actions)
    progress = np.arange(t) / max(t - 1, 1)
    phase = gripper_phases(actions[:, gripper_dim] > 0) if gripper_dim is not None else ["none"] * t
    return pd.DataFrame(
        {
            "task_id": task,
            "episode_index": episode,
            "frame_index": np.arange(t),
            "progress": progress,
            "fifth": np.minimum((progress * FIFTHS).astype(int), FIFTHS - 1),
            "phase": phase,
        }
    )


def dataset_frames(
    root: str | Path,
    *,
    every: int = 1,
    gripper_dim: int | None = -1,
    max_episodes: int | None = None,
) -> FrameSet:
    """The frames of the LeRobotDataset at ``root`` (every ``every``-th frame of each episode,
    the last always kept), read offline. Images are the dataset's camera keys
    (``observation.image`` -> camera ``image``, ``observation.images.<cam>`` -> ``cam``)."""
    from pipeline.api.offline import hf_offline

    root = Path(root)
    if not (root / "meta" / "info.json").is_file():
        raise ConfigError(
            f"frames: {root} is not a LeRobotDataset (no meta/info.json); record held-out "
            "demonstrations first, e.g. python -m training.metaworld_demos --root "
            f"{root} --episodes 5 --first-episode 200000"
        )
    if every < 1:
        raise ConfigError(f"every={every} must be >= 1")
    with hf_offline():
        from lerobot.datasets.lerobot_dataset import LeRobotDataset

        ds = LeRobotDataset(f"local/{root.name}", root=root)
    cams = {
        k: camera_of(k) or k for k, f in ds.features.items() if f.get("dtype") in ("image", "video")
    }
    table = ds.hf_dataset.with_format(None)
    episodes = np.asarray(table["episode_index"])
    chosen, metas = [], []
    for n_ep, ep in enumerate(np.unique(episodes)):
        if max_episodes is not None and n_ep >= max_episodes:
            break
        idx = np.flatnonzero(episodes == ep)
        actions = np.asarray([np.asarray(table[int(i)][ACTION]) for i in idx], dtype=np.float32)
        task = str(ds[int(idx[0])]["task"])
        meta = episode_meta(task, int(ep), actions, gripper_dim)
        keep = sorted({*range(0, len(idx), every), len(idx) - 1})
        chosen += [int(idx[k]) for k in keep]
        metas.append(meta.iloc[keep])
    if not chosen:
        raise ConfigError(f"frames: {root} holds no episode")
    images: dict[str, list[np.ndarray]] = {c: [] for c in cams.values()}
    states, texts = [], []
    for i in chosen:
        item = ds[i]
        for key, cam in cams.items():
            images[cam].append(np.asarray(item[key], dtype=np.float32))
        states.append(np.asarray(item[OBS_STATE], dtype=np.float32))
        texts.append(str(item["task"]))
    frames = {
        "images": {c: np.stack(v) for c, v in images.items()},
        "state": np.stack(states),
        "instruction": texts,
    }
    meta = pd.concat(metas, ignore_index=True)
    return FrameSet(frames, meta, str(root))
