"""The tiny VLA's demonstrations as tensors (``training.train_tiny_vla``): LeRobotDataset
folders read whole with pyarrow, their PNG frames decoded once into uint8 tensors, each frame's
action chunk as frame indices within its episode, and the words of the instructions (the net's
vocabulary)."""

from __future__ import annotations

import io
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from idr_core.features import ACTION, IMAGE_PREFIX, OBS_STATE


@dataclass
class DemoTensors:
    images: dict[str, torch.Tensor]  # key -> uint8 (N, 3, H, W)
    state: torch.Tensor  # (N, S)
    action: torch.Tensor  # (N, D)
    tasks: list[str]  # per frame
    chunk_index: (
        torch.Tensor
    )  # (N, T) frame indices of each frame's action chunk (clamped in episode)
    chunk_pad: torch.Tensor  # (N, T) True where the chunk ran past the episode end
    n_episodes: int


def _decode(png: bytes) -> np.ndarray:
    from PIL import Image

    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.uint8).transpose(2, 0, 1)


def load_demos(roots: list[Path], chunk: int) -> DemoTensors:
    """Read LeRobotDataset folders (v3 layout: data/chunk-*/file-*.parquet, meta/tasks.parquet)
    with pyarrow, decoding the PNG frames once: ~100x faster than per-item dataset access."""
    import pandas as pd
    import pyarrow.parquet as pq

    images: dict[str, list[np.ndarray]] = {}
    state, action, tasks, episode = [], [], [], []
    offset = 0
    for root in roots:
        files = sorted((root / "data").glob("chunk-*/*.parquet"))
        if not files:
            raise FileNotFoundError(
                f"{root} holds no LeRobotDataset data files (data/chunk-*/*.parquet)"
            )
        table = pq.read_table(files)
        task_names = pd.read_parquet(root / "meta" / "tasks.parquet")
        by_index = {int(i): str(name) for name, i in task_names["task_index"].items()}
        for k in [c for c in table.column_names if c.startswith(IMAGE_PREFIX)]:
            images.setdefault(k, []).extend(
                _decode(v["bytes"]) for v in table.column(k).to_pylist()
            )
        state.append(np.asarray(table.column(OBS_STATE).to_pylist(), dtype=np.float32))
        action.append(np.asarray(table.column(ACTION).to_pylist(), dtype=np.float32))
        tasks.extend(by_index[int(t)] for t in table.column("task_index").to_pylist())
        episode.append(
            np.asarray(table.column("episode_index").to_pylist(), dtype=np.int64) + offset
        )
        offset = int(episode[-1].max()) + 1
    ep = np.concatenate(episode)
    n = len(ep)
    idx = np.arange(n)[:, None] + np.arange(chunk)[None]
    idx = np.minimum(idx, n - 1)
    pad = ep[idx] != ep[:, None]
    # clamp to the episode's last frame
    last = np.zeros(n, dtype=np.int64)
    for e in np.unique(ep):
        members = np.flatnonzero(ep == e)
        last[members] = members[-1]
    idx = np.minimum(idx, last[:, None])
    return DemoTensors(
        images={k: torch.from_numpy(np.stack(v)) for k, v in images.items()},
        state=torch.from_numpy(np.concatenate(state)),
        action=torch.from_numpy(np.concatenate(action)),
        tasks=tasks,
        chunk_index=torch.from_numpy(idx),
        chunk_pad=torch.from_numpy(pad),
        n_episodes=len(np.unique(ep)),
    )


def vocabulary(tasks: list[str]) -> list[str]:
    return sorted({w for t in set(tasks) for w in re.findall(r"[a-z]+", t.lower())})
