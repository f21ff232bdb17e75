"""What a perturbation costs: the tabletop's reset and step (with the agent view and wrist
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--steps", type=int, default=40)
    args = ap.parse_args()

    from workers.rendering import configure_rendering

    configure_rendering()
    from workers.envs.perturbations import PerturbedEnv, parse
    from workers.envs.tabletop import TabletopEnv

    env = PerturbedEnv(TabletopEnv(image_size=96), [parse(c) for c in CASES])
    action = np.array([0.2, 0.0, -0.1, 0.0, 0.0, 0.0, -1.0])

    def read(obs) -> None:
        for cam in ("agentview", "wrist"):
            obs.images[cam]

    env.reset("pick_color", 99, 0)  # build the scene once, outside the timings
    out: dict[str, dict[str, float]] = {}
    for _ in range(2):  # a warm-up round, then the measured one (same order)
        for case in CASES:
            task = "pick_color" if case == "none" else f"pick_color@{case}"
            resets, steps = [], []
            for e in range(args.episodes):
                t0 = time.perf_counter()
                read(env.reset(task, e, 0))
                resets.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                for _ in range(args.steps):
                    read(env.step(action))
                steps.append((time.perf_counter() - t0) / args.steps)
            out[case] = {
                "reset_ms": 1e3 * float(np.median(resets)),
                "step_ms": 1e3 * float(np.median(steps)),
            }
    env.close()
    base = out["none"]
    result = {
        "cases": {
            c: {
                **{k: round(v, 2) for k, v in m.items()},
                "reset_ratio": round(m["reset_ms"] / base["reset_ms"], 3),
                "step_ratio": round(m["step_ms"] / base["step_ms"], 3),
            }
            for c, m in out.items()
        },
        "episodes": args.episodes,
        "steps_per_episode": args.steps,
        "image_size": 96,
        "machine": f"{platform.machine()}, {platform.python_version()}",
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
