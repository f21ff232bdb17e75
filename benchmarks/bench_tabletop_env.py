"""Tabletop env speed: physics alone vs rendering, 1 vs 2 cameras, 64/128/224 px, fast vs default look.

Each measurement steps one task with zero actions; rendering is forced on every step by reading
the images (in a run, images are read only when the backbone infers). Writes
``benchmarks/results/tabletop_env.json``.
Usage: ``python benchmarks/bench_tabletop_env.py [--steps 40]``
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

RESULTS = Path(__file__).parent / "results" / "tabletop_env.json"


def measure(
    task: str, steps: int, image_size: int, cameras: tuple[str, ...], render: bool, fast: bool
) -> float:
    from workers.envs.suites.tabletop.env import TabletopEnv

    env = TabletopEnv(image_size=image_size, cameras=cameras, fast_render=fast)
    try:
        obs = env.reset(task, 0, 0)
        for cam in cameras:
            obs.images[cam]  # warm the GL context
        t0 = time.perf_counter()
        for _ in range(steps):
            obs = env.step(np.zeros(7))
            if render:
                for cam in cameras:
                    obs.images[cam]
        return (time.perf_counter() - t0) / steps * 1e3
    finally:
        env.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    from workers.rendering import configure_rendering

    backend = configure_rendering()
    rows: list[dict[str, Any]] = []

    def add(task: str, size: int, cams: tuple[str, ...], render: bool, fast: bool) -> None:
        ms = measure(task, args.steps, size, cams, render, fast)
        rows.append(
            {
                "task": task,
                "image_size": size,
                "cameras": len(cams) if render else 0,
                "look": ("fast" if fast else "default") if render else "-",
                "ms_per_step": ms,
                "steps_per_s": 1e3 / ms,
            }
        )
        r = rows[-1]
        print(
            f"{task:<12} {r['cameras']} cam {size:>4}px {r['look']:<8} {ms:7.1f} ms/step {r['steps_per_s']:6.1f} steps/s",
            flush=True,
        )

    for task in ("pick_color", "stack_color", "organize"):
        add(task, 96, ("agentview",), render=False, fast=True)
        for cams in (("agentview",), ("agentview", "wrist")):
            add(task, 96, cams, render=True, fast=True)
    for size in (64, 128, 224):
        for cams in (("agentview",), ("agentview", "wrist")):
            for fast in (True, False):
                add("pick_color", size, cams, render=True, fast=fast)
    out = {
        "backend": backend,
        "lp_num_threads": os.environ.get("LP_NUM_THREADS"),
        "steps": args.steps,
        "rows": rows,
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
