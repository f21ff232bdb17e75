"""CALVIN env speed, in its env server (Python 3.11) as a run uses it: per step without
rendering (physics + the oracle: steps a chunk executes open-loop), per step with both cameras
rendered (a step an inference follows), and the reset of a new sequence (a rebuilt simulator),
for PyBullet's EGL and TinyRenderer. One server process = one core.
Writes ``benchmarks/results/calvin_env.json``; skipped (exit 0) without .venv-calvin or CALVIN_ENV.
Usage: ``CALVIN_ENV=... python benchmarks/bench_calvin_env.py [--steps 120]``
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "calvin_env.json"
PYTHON = Path(os.environ.get("IDR_CALVIN_PYTHON", ROOT / ".venv-calvin" / "bin" / "python"))


def measure(renderer: str, steps: int) -> dict[str, float]:
    from workers.envs.server.client import EnvServerClient, ServerSpec

    t0 = time.perf_counter()
    env = EnvServerClient(
        "workers.envs.suites.calvin.env:CalvinEnv",
        {"renderer": renderer},
        ServerSpec(str(PYTHON), 300),
    )
    start = time.perf_counter() - t0
    actions = np.random.default_rng(0).uniform(-0.3, 0.3, (steps, 7))
    try:
        t0 = time.perf_counter()
        env.reset("scene_D", 0, 0)
        first_reset = time.perf_counter() - t0
        t0 = time.perf_counter()
        for a in actions:
            env.step(a)
        open_loop = (time.perf_counter() - t0) / steps
        resets = []
        for e in (1, 2, 3):
            t0 = time.perf_counter()
            env.reset("scene_D", e, 0)
            resets.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for a in actions:
            obs = env.step(a)
            for cam in env.cameras:
                obs.images[cam]
        rendered = (time.perf_counter() - t0) / steps
    finally:
        env.close()
    return {
        "server_start_and_build_s": start,
        "first_reset_s": first_reset,
        "new_sequence_reset_s": float(np.median(resets)),
        "open_loop_ms_per_step": open_loop * 1e3,
        "rendered_ms_per_step": rendered * 1e3,
        "rendered_steps_per_s_per_core": 1 / rendered,
        "open_loop_steps_per_s_per_core": 1 / open_loop,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=120)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    if not PYTHON.exists() or not os.environ.get("CALVIN_ENV"):
        print(f"skipped: needs {PYTHON} (make setup-calvin) and CALVIN_ENV (a calvin_env checkout)")
        return
    rows = {}
    for renderer in ("tiny", "egl"):
        rows[renderer] = r = measure(renderer, args.steps)
        print(
            f"{renderer:<5} open-loop {r['open_loop_ms_per_step']:6.1f} ms/step  rendered "
            f"{r['rendered_ms_per_step']:6.1f} ms/step ({r['rendered_steps_per_s_per_core']:.1f} "
            f"steps/s/core)  new sequence {r['new_sequence_reset_s']:.2f} s  server start "
            f"{r['server_start_and_build_s']:.2f} s",
            flush=True,
        )
    out = {
        "what": "CALVIN scene D through its env server; rendered = rgb_static 200 px + "
        "rgb_gripper 84 px read every step; a new sequence rebuilds the simulator",
        "steps": args.steps,
        "renderers": rows,
        "machine": machine_record(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
