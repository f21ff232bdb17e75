"""Episode videos: one camera's frames, from the reset to the last step, written as MP4.

What a lerobot-eval user expects to look at: ``RUN_DIR/videos/cell=<cell>/<task>/
episode_<i>.mp4`` for the first ``videos.episodes`` episodes of each task and cell (the
tracker logs them as artifacts of the cell's MLflow run). Written to a temporary name and
renamed, so a video is whole or absent. Encoded with imageio's ffmpeg (libx264, yuv420p).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np


def video_path(video_dir: str | Path, cell_id: str, task_id: str, episode_index: int) -> Path:
    task = task_id.replace("/", "_").replace("@", "_at_").replace(":", "_")
    return Path(video_dir) / f"cell={cell_id}" / task / f"episode_{episode_index}.mp4"


class EpisodeVideo:
    """Frames of one episode's camera, written once the episode ends."""

    def __init__(self, path: Path, camera: str, fps: float) -> None:
        self.path, self.camera, self.fps = path, camera, fps
        self.frames: list[np.ndarray] = []

    def add(self, obs: Any) -> None:
        self.frames.append(np.asarray(obs.images[self.camera], dtype=np.uint8))

    def write(self) -> Path | None:
        if not self.frames:
            return None
        import imageio.v2 as imageio

        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_name(f".{self.path.name}.{os.getpid()}.tmp.mp4")
        frames = [_even(f) for f in self.frames]
        with imageio.get_writer(
            tmp, fps=self.fps, codec="libx264", pixelformat="yuv420p", macro_block_size=1
        ) as writer:
            for frame in frames:
                writer.append_data(frame)
        os.replace(tmp, self.path)
        return self.path


def _even(frame: np.ndarray) -> np.ndarray:
    """yuv420p needs even sides: a last row / column is dropped where one is odd."""
    h, w = frame.shape[:2]
    return frame[: h - h % 2, : w - w % 2]
