"""What a perturbation costs: the tabletop's (and LIBERO's scene kinds') reset and step (with the agent view and wrist
images read, as a policy reads them), unperturbed and under each kind, measured in one process
in one run (ratios, not absolute targets).

Writes ``benchmarks/results/perturbations.json``. Usage:
``python benchmarks/bench_perturbations.py [--episodes 4] [--steps 40]``
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = Path(__file__).parent / "results" / "perturbations.json"
CASES = [
    "none",
    "camera_shift:0.16",
    "camera_pitch:15",
    "light_dim:0.36",
    "table_color:0.65",
    "init_jitter:0.02",
    "image_noise:0.3",
    "image_blur:1.5",
]


LIBERO_CASES = [c for c in CASES if not c.startswith("image_")]


def measure(env, task: str, cases: list[str], episodes: int, steps: int) -> dict:
    """Median reset and per-step ms per case (images read), after a warm-up round."""
    action = np.array([0.2, 0.0, -0.1, 0.0, 0.0, 0.0, -1.0])

    def read(obs) -> None:
        for cam in ("agentview", "wrist"):
            obs.images[cam]

    env.reset(task, 99, 0)  # build the scene once, outside the timings
    out: dict[str, dict[str, float]] = {}
    for _ in range(2):  # a warm-up round, then the measured one (same order)
        for case in cases:
            task_id = task if case == "none" else f"{task}@{case}"
            resets, times = [], []
            for e in range(episodes):
                t0 = time.perf_counter()
                read(env.reset(task_id, e, 0))
                resets.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                for _ in range(steps):
                    read(env.step(action))
                times.append((time.perf_counter() - t0) / steps)
            out[case] = {
                "reset_ms": 1e3 * float(np.median(resets)),
                "step_ms": 1e3 * float(np.median(times)),
            }
    env.close()
    base = out["none"]
    return {
        c: {
            **{k: round(v, 2) for k, v in m.items()},
            "reset_ratio": round(m["reset_ms"] / base["reset_ms"], 3),
            "step_ratio": round(m["step_ms"] / base["step_ms"], 3),
        }
        for c, m in out.items()
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--libero-episodes", type=int, default=2, help="0: skip LIBERO")
    args = ap.parse_args()

    from workers.rendering import configure_rendering

    configure_rendering()
    from workers.envs.suites.tabletop.env import TabletopEnv
    from workers.envs.wrappers.perturbation_grammar import parse
    from workers.envs.wrappers.perturbations import PerturbedEnv

    env = PerturbedEnv(TabletopEnv(image_size=96), [parse(c) for c in CASES])
    result: dict = {
        "cases": measure(env, "pick_color", CASES, args.episodes, args.steps),
        "episodes": args.episodes,
        "steps_per_episode": args.steps,
        "image_size": 96,
    }
    if args.libero_episodes:
        from workers.envs.suites.libero.env import LiberoEnv

        libero = LiberoEnv(suites=("libero_spatial",), image_size=128)
        env = PerturbedEnv(libero, [parse(c) for c in LIBERO_CASES])
        result["libero"] = {
            "task": "libero_spatial/0 (openpi protocol: a hard reset rebuilds the model)",
            "cases": measure(env, "libero_spatial/0", LIBERO_CASES, args.libero_episodes, 10),
            "episodes": args.libero_episodes,
            "steps_per_episode": 10,
            "image_size": 128,
        }
    result["machine"] = f"{platform.machine()}, {platform.python_version()}"
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
