"""LIBERO env speed: control steps per second for one task, rendering off vs on, 1 vs 2 cameras,
several image sizes (the render size; 256 px is the openpi / OFT protocol's).

Each configuration builds its own ``LiberoEnv`` (the render size is fixed when the simulator is
built), resets it once (a hard reset plus the 10 protocol no-ops) and times ``--steps`` control
steps of a small back-and-forth end-effector motion. Setup and reset times are recorded too.
The machine's load is recorded with the figures: on a shared CPU they are noisy.

Writes ``benchmarks/results/libero_env.json``. Usage: ``python benchmarks/bench_libero_env.py``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np

from workers.rendering import configure_rendering

RESULTS = Path(__file__).parent / "results" / "libero_env.json"
TASK = "libero_spatial/0"


def _actions(n: int) -> np.ndarray:
    """Small +-x/+-y end-effector deltas, gripper open: the arm moves, nothing is grasped."""
    t = np.arange(n)
    a = np.zeros((n, 7), dtype=np.float32)
    a[:, 0] = 0.3 * np.sin(t / 4)
    a[:, 1] = 0.3 * np.cos(t / 4)
    a[:, 6] = -1.0
    return a


def measure(cameras: tuple[str, ...], image_size: int, steps: int) -> dict[str, Any]:
    from workers.envs.libero import LiberoEnv

    env = LiberoEnv(suites=["libero_spatial"], image_size=image_size, cameras=cameras)
    try:
        t0 = time.perf_counter()
        env.reset(TASK, 0, 0)  # builds the simulator
        t1 = time.perf_counter()
        env.reset(TASK, 1, 0)  # a second reset: what each further episode costs
        t2 = time.perf_counter()
        for a in _actions(steps):
            env.step(a)
        t3 = time.perf_counter()
    finally:
        env.close()
    return {
        "cameras": list(cameras),
        "image_size": image_size if cameras else None,
        "steps": steps,
        "steps_per_second": steps / (t3 - t2),
        "ms_per_step": (t3 - t2) / steps * 1e3,
        "build_and_first_reset_s": t1 - t0,
        "reset_s": t2 - t1,
    }


def configurations(sizes: list[int]) -> list[tuple[tuple[str, ...], int]]:
    out: list[tuple[tuple[str, ...], int]] = [((), sizes[0])]  # size unused: nothing rendered
    for cams in (("agentview",), ("agentview", "wrist")):
        out += [(cams, s) for s in sizes]
    return out


def print_table(rows: list[dict[str, Any]]) -> None:
    print(f"{'cameras':<18}{'px':>5}{'steps/s':>10}{'ms/step':>10}{'build s':>9}{'reset s':>9}")
    for r in rows:
        cams = "+".join(r["cameras"]) or "(render off)"
        px = r["image_size"] or "-"
        print(
            f"{cams:<18}{px:>5}{r['steps_per_second']:>10.2f}{r['ms_per_step']:>10.1f}"
            f"{r['build_and_first_reset_s']:>9.1f}{r['reset_s']:>9.1f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 224, 256])
    args = ap.parse_args()
    backend = configure_rendering()
    res: dict[str, Any] = {
        "task": TASK,
        "machine": {
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "render_backend": backend,
            "LP_NUM_THREADS": os.environ.get("LP_NUM_THREADS"),
            "load_average_at_start": os.getloadavg(),
        },
        "results": [],
    }
    for cams, size in configurations(args.sizes):
        row = measure(cams, size, args.steps)
        res["results"].append(row)
        print(
            f"{'+'.join(cams) or 'render off'} {size if cams else ''}: {row['ms_per_step']:.1f} ms/step"
        )
    res["machine"]["load_average_at_end"] = os.getloadavg()
    print_table(res["results"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
