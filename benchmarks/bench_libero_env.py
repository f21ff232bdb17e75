"""LIBERO env speed: control steps per second for one task, rendering off vs on, 1 vs 2 cameras,
several image sizes (the render size; 256 px is the openpi / OFT protocol's), and eager vs lazy
rendering under the pipeline's read patterns.

``results`` (the sweep): each configuration builds its own ``LiberoEnv`` with eager rendering
(robosuite renders every camera on every step: the cost of rendering itself; the render size is
fixed when the simulator is built), resets it once (a hard reset plus the 10 protocol no-ops) and
times ``--steps`` control steps of a small back-and-forth end-effector motion. Setup and reset
times are recorded too.

``patterns``: at 256 px with both cameras, eager vs lazy rendering (``lazy_render``), with the
images of every camera read every step (closed loop) or every 8th step (an open-loop chunk of
8 actions, as the actor does: read, infer, execute the chunk). Each run resets (timed apart) and
times ``--pattern-steps`` steps, reads included; runs alternate eager / lazy, ``--repeats``
each. The images read are compared: lazy must give eager's pixels.

The machine's load is recorded with the figures: on a shared CPU they are noisy.

Writes ``benchmarks/results/libero_env.json``. Usage: ``python benchmarks/bench_libero_env.py``
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

import numpy as np

from workers.hardware import machine_record
from workers.rendering import configure_rendering

RESULTS = Path(__file__).parent / "results" / "libero_env.json"
TASK = "libero_spatial/0"
PATTERN_SIZE = 256
PATTERN_CAMERAS = ("agentview", "wrist")


def _actions(n: int) -> np.ndarray:
    """Small +-x/+-y end-effector deltas, gripper open: the arm moves, nothing is grasped."""
    t = np.arange(n)
    a = np.zeros((n, 7), dtype=np.float32)
    a[:, 0] = 0.3 * np.sin(t / 4)
    a[:, 1] = 0.3 * np.cos(t / 4)
    a[:, 6] = -1.0
    return a


def measure(cameras: tuple[str, ...], image_size: int, steps: int) -> dict[str, Any]:
    from workers.envs.suites.libero.env import LiberoEnv

    env = LiberoEnv(
        suites=["libero_spatial"], image_size=image_size, cameras=cameras, lazy_render=False
    )
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
        "lazy_render": False,
        "image_size": image_size if cameras else None,
        "steps": steps,
        "steps_per_second": steps / (t3 - t2),
        "ms_per_step": (t3 - t2) / steps * 1e3,
        "build_and_first_reset_s": t1 - t0,
        "reset_s": t2 - t1,
    }


def run_pattern(env: Any, read_every: int, steps: int) -> tuple[dict[str, float], list]:
    """One episode: reset (timed apart), then ``steps`` steps, reading every camera's image of
    the current observation before steps ``0, read_every, 2 * read_every, ...``."""
    t0 = time.perf_counter()
    obs = env.reset(TASK, 1, 0)
    t1 = time.perf_counter()
    read = []
    for i, a in enumerate(_actions(steps)):
        if i % read_every == 0:
            read.append({cam: obs.images[cam] for cam in env.cameras})
        obs = env.step(a)
    t2 = time.perf_counter()
    return {"reset_s": t1 - t0, "ms_per_step": (t2 - t1) / steps * 1e3}, read


def measure_patterns(steps: int, repeats: int, read_every: list[int]) -> list[dict[str, Any]]:
    from workers.envs.suites.libero.env import LiberoEnv

    envs = {
        lazy: LiberoEnv(
            suites=["libero_spatial"],
            image_size=PATTERN_SIZE,
            cameras=PATTERN_CAMERAS,
            lazy_render=lazy,
        )
        for lazy in (False, True)
    }
    rows = []
    try:
        for env in envs.values():
            env.reset(TASK, 0, 0)  # builds the simulator: not timed
        for every in read_every:
            runs: dict[bool, list[dict[str, float]]] = {False: [], True: []}
            images: dict[bool, list] = {}
            for _ in range(repeats):
                for lazy, env in envs.items():  # alternate: load drifts hit both alike
                    run, images[lazy] = run_pattern(env, every, steps)
                    runs[lazy].append(run)
            equal = all(
                np.array_equal(e[cam], z[cam])
                for e, z in zip(images[False], images[True], strict=True)
                for cam in PATTERN_CAMERAS
            )
            for lazy in (False, True):
                ms = [r["ms_per_step"] for r in runs[lazy]]
                rows.append(
                    {
                        "lazy_render": lazy,
                        "read_every": every,
                        "cameras": list(PATTERN_CAMERAS),
                        "image_size": PATTERN_SIZE,
                        "steps": steps,
                        "ms_per_step": statistics.median(ms),
                        "ms_per_step_runs": ms,
                        "reset_s": statistics.median(r["reset_s"] for r in runs[lazy]),
                        "images_read": len(images[lazy]) * len(PATTERN_CAMERAS),
                        "pixels_equal_eager": equal,
                    }
                )
                print(
                    f"{'lazy' if lazy else 'eager'} read every {every}: "
                    f"{rows[-1]['ms_per_step']:.1f} ms/step {ms}, pixels equal: {equal}"
                )
    finally:
        for env in envs.values():
            env.close()
    return rows


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


def print_patterns(rows: list[dict[str, Any]]) -> None:
    print(f"\n{'render':<8}{'read every':>11}{'ms/step':>10}{'reset s':>9}{'= eager':>9}")
    for r in rows:
        print(
            f"{'lazy' if r['lazy_render'] else 'eager':<8}{r['read_every']:>11}"
            f"{r['ms_per_step']:>10.1f}{r['reset_s']:>9.1f}{r['pixels_equal_eager']!s:>9}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--sizes", type=int, nargs="+", default=[64, 128, 224, 256])
    ap.add_argument("--pattern-steps", type=int, default=48)
    ap.add_argument("--read-every", type=int, nargs="+", default=[1, 8])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--no-sweep", action="store_true", help="only the eager vs lazy patterns")
    args = ap.parse_args()
    backend = configure_rendering()
    res: dict[str, Any] = {
        "task": TASK,
        "machine": {
            **machine_record(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
            "render_backend": backend,
            "LP_NUM_THREADS": os.environ.get("LP_NUM_THREADS"),
            "load_average_at_start": os.getloadavg(),
        },
        "results": [],
    }
    for cams, size in [] if args.no_sweep else configurations(args.sizes):
        row = measure(cams, size, args.steps)
        res["results"].append(row)
        print(
            f"{'+'.join(cams) or 'render off'} {size if cams else ''}: {row['ms_per_step']:.1f} ms/step"
        )
    res["patterns"] = measure_patterns(args.pattern_steps, args.repeats, args.read_every)
    res["machine"]["load_average_at_end"] = os.getloadavg()
    print_table(res["results"])
    print_patterns(res["patterns"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
