"""Record MetaWorld demonstrations with metaworld's own scripted experts as a LeRobotDataset.

The env is built from the ``env:`` block of a harness config (default ``conf/zoo/metaworld.yaml``:
the gymnasium suite over metaworld's env classes at 96 px), so the recorded frames, state and
instruction are exactly what an evaluation of that config shows the policy. The expert of each
task is ``metaworld.policies.<Task>Policy``, acting on the env's full 39-d state (objects and
goal included); the policy learns from the camera, the hand's 4-d state and the instruction.
Only successful episodes are kept. Init states come from episode ``--first-episode`` on
(100000 by default), never an evaluation's (evaluations use episodes 0 ... n-1).

    python -m training.metaworld_demos --root data/zoo/metaworld --episodes 40
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import time
from pathlib import Path
from typing import Any

import numpy as np
from idr_core.features import ACTION, OBS_IMAGE, OBS_STATE

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "conf" / "zoo" / "metaworld.yaml"
FPS = 80  # MetaWorld's control rate (lerobot's MetaWorld config says the same)


def expert_for(task: str):
    """metaworld's scripted policy of a v3 task (``drawer-open-v3`` -> SawyerDrawerOpenV3Policy)."""
    from metaworld import policies

    name = (
        "Sawyer" + "".join(p.capitalize() for p in task.replace("-v3", "").split("-")) + "V3Policy"
    )
    if not hasattr(policies, name):
        raise SystemExit(f"task {task!r}: metaworld.policies has no {name}")
    return getattr(policies, name)()


def env_from_config(path: Path):
    import yaml

    from workers.envs.gym_env import GymnasiumEnv

    env = yaml.safe_load(path.read_text())["env"]
    if env.get("suite") != "gymnasium":
        raise SystemExit(f"{path}: env.suite must be gymnasium (got {env.get('suite')!r})")
    return GymnasiumEnv(**env["params"]), list(env["tasks"])


def features(env) -> dict:
    (cam,) = env.cameras
    h, w = env.image_sizes[cam]
    return {
        OBS_IMAGE: {
            "dtype": "image",
            "shape": (h, w, 3),
            "names": ["height", "width", "channels"],
        },
        OBS_STATE: {"dtype": "float32", "shape": (env.state_dim,), "names": None},
        ACTION: {"dtype": "float32", "shape": (env.action_dim,), "names": None},
    }


def record(
    root: Path,
    episodes: int,
    config: Path = CONFIG,
    tasks: list[str] | None = None,
    seed: int = 0,
    first_episode: int = 100_000,
    repo_id: str = "local/zoo_metaworld",
) -> dict[str, dict[str, float]]:
    from workers.rendering import configure_rendering

    configure_rendering()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from training.tabletop_demos import defer_stop_signals

    env, all_tasks = env_from_config(config)
    tasks = tasks or all_tasks
    unknown = sorted(set(tasks) - {t.task_id for t in env.tasks()})
    if unknown:
        raise SystemExit(f"--tasks {unknown}: not tasks of {config}")
    if root.exists():
        shutil.rmtree(root)
    ds = LeRobotDataset.create(
        repo_id=repo_id,
        fps=FPS,
        features=features(env),
        root=root,
        robot_type="sawyer",
        use_videos=False,
    )
    stop, previous = defer_stop_signals()
    stats: dict[str, dict[str, float]] = {}
    try:
        for task in tasks:
            stats[task] = _record_task(ds, env, task, episodes, seed, first_episode, stop)
            print(
                f"{task}: {stats[task]['episodes']}/{stats[task]['tried']} kept, "
                f"{stats[task]['frames']} frames, {stats[task]['seconds']:.0f}s",
                flush=True,
            )
            if stop:
                break
    finally:
        try:
            env.close()
            ds.finalize()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    _write_parts(root, config, first_episode, stats)
    return stats


def _episode(env: Any, expert: Any, task: str, episode: int, seed: int) -> tuple[list[dict], bool]:
    """One episode the expert drives: its frames and whether it succeeded."""
    (cam,) = env.cameras
    obs = env.reset(task, episode, seed)
    buffer = []
    while not obs.status.done:
        action = np.clip(expert.get_action(env.raw_observation["state"]), -1, 1)
        action = action.astype(np.float32)
        buffer.append(
            {
                OBS_IMAGE: obs.images[cam],
                OBS_STATE: obs.state.astype(np.float32),
                ACTION: action,
                "task": obs.status.instruction,
            }
        )
        obs = env.step(action)
    return buffer, obs.status.success


def _record_task(
    ds: Any, env: Any, task: str, episodes: int, seed: int, first_episode: int, stop: list[int]
) -> dict[str, float]:
    """``episodes`` successful episodes of ``task`` added to ``ds``, or fewer once ``stop``
    holds a signal; the task's statistics."""
    expert = expert_for(task)
    kept, tried, frames, t0 = 0, 0, 0, time.perf_counter()
    while kept < episodes and not stop:
        buffer, success = _episode(env, expert, task, first_episode + tried, seed)
        tried += 1
        if not success:
            if tried > 2 * episodes + 10:
                raise RuntimeError(f"expert failed too often on {task}: {kept}/{tried}")
            continue
        for frame in buffer:
            ds.add_frame(frame)
        ds.save_episode()
        kept, frames = kept + 1, frames + len(buffer)
    return {
        "episodes": kept,
        "tried": tried,
        "frames": frames,
        "seconds": round(time.perf_counter() - t0, 1),
    }


def _write_parts(
    root: Path, config: Path, first_episode: int, stats: dict[str, dict[str, float]]
) -> None:
    """``meta/zoo_parts.json``: what the dataset holds (an export's card data)."""
    (root / "meta" / "zoo_parts.json").write_text(
        json.dumps(
            {
                "benchmark": "metaworld",
                "config": str(config.relative_to(ROOT) if config.is_relative_to(ROOT) else config),
                "episodes": sum(int(s["episodes"]) for s in stats.values()),
                "frames": sum(int(s["frames"]) for s in stats.values()),
                "first_episode": first_episode,
                "tasks": stats,
            },
            indent=2,
        )
        + "\n"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, default=ROOT / "data" / "zoo" / "metaworld")
    ap.add_argument("--episodes", type=int, default=40, help="successful episodes per task")
    ap.add_argument("--config", type=Path, default=CONFIG)
    ap.add_argument("--tasks", nargs="*", default=None)
    ap.add_argument("--first-episode", type=int, default=100_000)
    args = ap.parse_args()
    record(args.root, args.episodes, args.config, args.tasks, first_episode=args.first_episode)


if __name__ == "__main__":
    main()
