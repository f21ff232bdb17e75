"""Record scripted-expert demonstrations of the tabletop suite as a LeRobotDataset.

Each frame holds both camera images (uint8 HWC at ``image_size``, the look the env renders),
the 8-d state, the 7-d action the expert executed and the instruction as the frame's task.
Episode indices start at ``first_episode`` so demonstrations never share init states with
evaluation episodes (which start at 0) when ``first_episode`` is large.

Two ways to leave the expert's own state distribution, whose absence is why a cloned policy that
drifts a centimetre off the demonstrations never recovers (the frame's label is always the
expert's action at the state actually visited; the expert is a stateless feedback rule, so it
can label any state):

* ``noise`` (DART, Laskey et al. 2017): the executed action is the expert's plus Gaussian noise
  on the translation dims; only successful episodes are kept.
* ``policy`` (DAgger, Ross et al. 2011): a lerobot checkpoint drives the robot (chunks of
  ``replan_steps``) while the expert labels every visited state; episodes are kept whatever
  their outcome, since the labels are what matter.

    python -m training.tabletop_demos --root data/tabletop_demos --episodes 40 \
        --tasks pick_color stack_color organize --image-size 96
"""

from __future__ import annotations

import argparse
import shutil
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from idr_core.features import ACTION, IMAGE_PREFIX, OBS_STATE

CAMERA_KEYS = {"agentview": f"{IMAGE_PREFIX}agentview", "wrist": f"{IMAGE_PREFIX}wrist"}


def defer_stop_signals() -> tuple[list[int], dict]:
    """SIGINT / SIGTERM recorded in the returned list instead of raising (a recorder stops after
    the episode in progress and still finalizes its dataset); the previous handlers, to restore."""
    stop: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        return stop, {}
    previous = {
        sig: signal.signal(sig, lambda signum, _frame: stop.append(signum))
        for sig in (signal.SIGINT, signal.SIGTERM)
    }
    return stop, previous


def features(image_size: int, cameras: tuple[str, ...]) -> dict:
    feats = {
        CAMERA_KEYS[c]: {
            "dtype": "image",
            "shape": (image_size, image_size, 3),
            "names": ["height", "width", "channels"],
        }
        for c in cameras
    }
    feats[OBS_STATE] = {"dtype": "float32", "shape": (8,), "names": None}
    feats[ACTION] = {"dtype": "float32", "shape": (7,), "names": None}
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
    noise: float = 0.0,
    policy: Path | None = None,
    replan_steps: int = 4,
    place_tol: float | None = None,
) -> dict[str, dict[str, float]]:
    """Record ``episodes`` demonstrations per task (successful ones unless ``policy`` drives);
    returns per-task statistics."""
    from workers.rendering import configure_rendering

    configure_rendering()
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from workers.envs.suites.tabletop.env import TabletopEnv
    from workers.experts.tabletop import PLACE_TOL

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
    driver = None
    if policy is not None:
        from workers.backbones.lerobot.adapter import LerobotBackbone

        driver = LerobotBackbone(path=str(policy), device="cpu")
    place_tol = PLACE_TOL if place_tol is None else place_tol
    rng = np.random.default_rng([seed, first_episode])
    rollout = _Rollout(env, cameras, place_tol, driver, replan_steps, noise, rng)
    stats: dict[str, dict[str, float]] = {}
    # SIGINT / SIGTERM stop after the episode in progress and still finalize the dataset (some
    # library in the stack swallows KeyboardInterrupt, and an unfinalized dataset is unreadable)
    stop, previous = defer_stop_signals()
    try:
        for task in tasks:
            if stop:
                break
            stats[task] = _record_task(ds, rollout, task, episodes, seed, first_episode, stop)
            print(
                f"{task}: {stats[task]['episodes']}/{stats[task]['tried']} kept, "
                f"{stats[task]['frames']} frames, {stats[task]['seconds']:.0f}s",
                flush=True,
            )
    finally:
        # signals stay deferred until the dataset is finalized: a second Ctrl-C (or a scheduler
        # repeating SIGTERM) during finalize would otherwise leave it unreadable
        try:
            env.close()
            ds.finalize()
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
    if stop:
        print(f"stopped by signal {stop[0]}: {stats}", flush=True)
    return stats


@dataclass(frozen=True)
class _Rollout:
    """How an episode is driven and labelled: the expert labels every visited state; the
    executed action is the expert's (plus DART's ``noise``) or, with a ``driver`` (DAgger), the
    policy's chunks of ``replan_steps``."""

    env: Any
    cameras: tuple[str, ...]
    place_tol: float
    driver: Any  # a LerobotBackbone, or None: the expert drives
    replan_steps: int
    noise: float
    rng: np.random.Generator

    def episode(self, task: str, episode: int, seed: int) -> tuple[list[dict], bool]:
        """The frames of one episode (the expert's labels) and whether it succeeded."""
        from workers.episode.observation import to_policy_observation
        from workers.experts.tabletop import expert_action

        env, driver = self.env, self.driver
        obs = env.reset(task, episode, seed)
        buffer, queue = [], []
        if driver is not None:
            driver.reset()
        while not obs.status.done:
            action = expert_action(obs.privileged, self.place_tol).astype(np.float32)
            frame = {CAMERA_KEYS[c]: obs.images[c] for c in self.cameras}
            frame.update(
                {
                    OBS_STATE: obs.state,
                    ACTION: action,
                    "task": obs.status.instruction,
                }
            )
            buffer.append(frame)
            executed = action.copy()
            if driver is not None:
                if not queue:
                    batch = to_policy_observation(obs, obs.status.instruction, driver.cameras)
                    chunk = driver.predict_chunk(batch)[0, : self.replan_steps]
                    queue = list(chunk.numpy().astype(np.float32))
                executed = queue.pop(0)
            if self.noise:
                executed[:3] = np.clip(executed[:3] + self.rng.normal(0, self.noise, 3), -1, 1)
            obs = env.step(executed)
        return buffer, obs.status.success


def _record_task(
    ds: Any,
    rollout: _Rollout,
    task: str,
    episodes: int,
    seed: int,
    first_episode: int,
    stop: list[int],
) -> dict[str, float]:
    """``episodes`` episodes of ``task`` added to ``ds`` (successful ones unless a policy
    drives), or fewer once ``stop`` holds a signal; the task's statistics."""
    kept, tried, frames, t0 = 0, 0, 0, time.perf_counter()
    while kept < episodes and not stop:
        buffer, success = rollout.episode(task, first_episode + tried, seed)
        tried += 1
        if rollout.driver is None and not success:
            continue
        for frame in buffer:
            ds.add_frame(frame)
        ds.save_episode()
        kept += 1
        frames += len(buffer)
        if tried > 2 * episodes + 10:
            raise RuntimeError(f"expert failed too often on {task}: {kept}/{tried}")
    return {
        "episodes": kept,
        "tried": tried,
        "frames": frames,
        "seconds": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", type=Path, required=True)
    ap.add_argument("--episodes", type=int, default=40, help="successful episodes per task")
    ap.add_argument("--tasks", nargs="+", default=["pick_color", "stack_color", "organize"])
    ap.add_argument("--image-size", type=int, default=96)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--first-episode", type=int, default=100_000)
    ap.add_argument(
        "--noise", type=float, default=0.0, help="DART: std of noise added to executed xyz"
    )
    ap.add_argument(
        "--policy", type=Path, default=None, help="DAgger: checkpoint that drives (expert labels)"
    )
    ap.add_argument("--replan-steps", type=int, default=4)
    ap.add_argument(
        "--place-tol",
        type=float,
        default=None,
        help="expert: xy distance (m) to the goal at which a held cube is lowered (default 0.0096)",
    )
    args = ap.parse_args()
    record(
        args.root,
        args.tasks,
        args.episodes,
        args.image_size,
        seed=args.seed,
        first_episode=args.first_episode,
        noise=args.noise,
        policy=args.policy,
        replan_steps=args.replan_steps,
        place_tol=args.place_tol,
    )


if __name__ == "__main__":
    main()
