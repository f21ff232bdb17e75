"""Record scripted-expert demonstrations of the tabletop suite as a LeRobotDataset.

Each frame holds both camera images (uint8 HWC at ``image_size``, the look the env renders),
the 8-d state, the 7-d action the expert executed and the instruction as the frame's task.
Only successful episodes are kept (the expert succeeds in nearly all of them); episode indices
start at ``first_episode`` so demonstrations never share init states with evaluation episodes
(which start at 0) when ``first_episode`` is large.

    python -m workers.envs.tabletop_demos --root data/tabletop_demos --episodes 40 \
        --tasks pick_color stack_color organize --image-size 96
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

import numpy as np

CAMERA_KEYS = {"agentview": "observation.images.agentview", "wrist": "observation.images.wrist"}


def features(image_size: int, cameras: tuple[str, ...]) -> dict:
    feats = {
        CAMERA_KEYS[c]: {
            "dtype": "image",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channels"],
        }
        for c in cameras
    }
    feats["observation.state"] = {"dtype": "float32", "shape": (8,), "names": None}
    feats["action"] = {"dtype": "float32", "shape": (7,), "names": None}
    return feats


def record(
    root: Path,
    tasks: list[str],
    episodes: int,
    image_size: int = 96,
    cameras: tuple[str, ...] = ("agentview", "wrist"),
    seed: int = 0,
    first_episode: int = 100_000,
    repo_id: str = "local/tabletop_demos",
) -> dict[str, dict[str, float]]:
    """Record ``episodes`` successful demonstrations per task; returns per-task statistics."""
    from workers.rendering import configure_rendering

    configure_rendering()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from workers.envs.tabletop import TabletopEnv
    from workers.envs.tabletop_experts import expert_action

    if root.exists():
        shutil.rmtree(root)
    ds = LeRobotDataset.create(
        repo_id=repo_id,
        fps=20,
        features=features(image_size, cameras),
        root=root,
        robot_type="panda",
        use_videos=False,
    )
    env = TabletopEnv(image_size=image_size, cameras=cameras)
    stats: dict[str, dict[str, float]] = {}
    try:
        for task in tasks:
            kept, tried, frames, t0 = 0, 0, 0, time.perf_counter()
            while kept < episodes:
                obs = env.reset(task, first_episode + tried, seed)
                tried += 1
                buffer = []
                while not env.done:
                    action = expert_action(obs.privileged).astype(np.float32)
                    frame = {CAMERA_KEYS[c]: obs.images[c] for c in cameras}
                    frame.update(
                        {"observation.state": obs.state, "action": action, "task": env.instruction}
                    )
                    buffer.append(frame)
                    obs = env.step(action)
                if not env.success:
                    continue
                for frame in buffer:
                    ds.add_frame(frame)
                ds.save_episode()
                kept += 1
                frames += len(buffer)
                if tried > 2 * episodes + 10:
                    raise RuntimeError(f"expert failed too often on {task}: {kept}/{tried}")
            stats[task] = {
                "episodes": kept,
                "tried": tried,
                "frames": frames,
                "seconds": time.perf_counter() - t0,
            }
            print(
                f"{task}: {kept}/{tried} kept, {frames} frames, {stats[task]['seconds']:.0f}s",
                flush=True,
            )
    finally:
        env.close()
        ds.finalize()
    return stats


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--episodes", type=int, default=40, help="successful episodes per task")
    ap.add_argument("--tasks", nargs="+", default=["pick_color", "stack_color", "organize"])
    ap.add_argument("--image-size", type=int, default=96)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--first-episode", type=int, default=100_000)
    args = ap.parse_args()
    record(
        args.root,
        args.tasks,
        args.episodes,
        args.image_size,
        seed=args.seed,
        first_episode=args.first_episode,
    )


if __name__ == "__main__":
    main()
