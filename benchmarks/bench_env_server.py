"""Env server overhead: the same tabletop env in the actor's process vs behind an env server.

Both envs are built with the same params and driven with the same random actions from the same
reset; every state and every image read is compared (they must be identical). Two kinds of
step, as in a run: open-loop (nobody reads the images; most steps of a chunk) and rendered
(both cameras read: the step an inference follows). Rounds alternate in-process and server,
so drift of this noisy machine hits both. Overhead = server - in-process, per step.
Writes ``benchmarks/results/env_server.json``.
Usage: ``python benchmarks/bench_env_server.py [--steps 60] [--rounds 3]``
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from workers.hardware import machine_record

RESULTS = Path(__file__).parent / "results" / "env_server.json"
PARAMS = {"image_size": 96, "cameras": ["agentview", "wrist"]}


def run(env: Any, actions: np.ndarray, render: bool) -> tuple[float, list[np.ndarray]]:
    """ms per step, and what was observed (states, and images when rendered)."""
    seen: list[np.ndarray] = []
    obs = env.reset("pick_color", 0, 0)
    for cam in env.cameras:
        obs.images[cam]  # warm: GL context, first frame
    t0 = time.perf_counter()
    for a in actions:
        obs = env.step(a)
        seen.append(obs.state)
        if render:
            seen.extend(obs.images[cam] for cam in env.cameras)
    return (time.perf_counter() - t0) / len(actions) * 1e3, seen


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    from workers.rendering import configure_rendering

    backend = configure_rendering()
    from workers.envs.server.client import EnvServerClient, ServerSpec
    from workers.envs.suites.tabletop.env import TabletopEnv

    actions = np.random.default_rng(0).uniform(-1, 1, (args.steps, 7)).astype(np.float32)
    local = TabletopEnv(**PARAMS)
    t0 = time.perf_counter()
    remote = EnvServerClient(
        "workers.envs.suites.tabletop.env:TabletopEnv", PARAMS, ServerSpec(sys.executable)
    )
    start_s = time.perf_counter() - t0
    times: dict[str, dict[str, list[float]]] = {
        kind: {"in_process": [], "server": []} for kind in ("open_loop", "rendered")
    }
    identical = True
    try:
        for _ in range(args.rounds):
            for kind, render in (("open_loop", False), ("rendered", True)):
                ms_local, seen_local = run(local, actions, render)
                ms_remote, seen_remote = run(remote, actions, render)
                identical &= all(
                    np.array_equal(a, b) for a, b in zip(seen_local, seen_remote, strict=True)
                )
                times[kind]["in_process"].append(ms_local)
                times[kind]["server"].append(ms_remote)
    finally:
        local.close()
        remote.close()

    # the protocol alone: a fake env whose step costs ~0.1 ms, many steps
    from workers.envs.fakes import FakeMarkerEnv

    fake_actions = np.zeros((2000, 2), dtype=np.float32)
    fakes = (
        FakeMarkerEnv(),
        EnvServerClient("workers.envs.fakes:FakeMarkerEnv", {}, ServerSpec(sys.executable)),
    )
    fake_ms = []
    try:
        for env in fakes:
            t0, n = time.perf_counter(), 0
            for _ in range(args.rounds):
                obs = env.reset("reach_chain", 0, 0)
                for a in fake_actions:
                    if obs.status.done:
                        obs = env.reset("reach_chain", 0, 0)
                    obs = env.step(a)
                    n += 1
            fake_ms.append((time.perf_counter() - t0) / n * 1e3)
    finally:
        fakes[1].close()
    times["protocol_fake_env"] = {"in_process": [fake_ms[0]], "server": [fake_ms[1]]}

    rows = {}
    for kind, t in times.items():
        a, b = float(np.median(t["in_process"])), float(np.median(t["server"]))
        rows[kind] = {
            "in_process_ms": a,
            "server_ms": b,
            "overhead_ms": b - a,
            "overhead_pct": 100 * (b - a) / a,
        }
        print(
            f"{kind:<17} in-process {a:7.2f} ms/step  server {b:7.2f} ms/step  overhead "
            f"{b - a:+6.2f} ms ({100 * (b - a) / a:+5.1f}%)"
        )
    print(f"server start + env build: {start_s:.2f} s; identical states and pixels: {identical}")
    out = {
        "what": "tabletop pick_color, 96 px, agentview + wrist; the same env in-process vs in an "
        "env server (this Python, a child process); medians over rounds. protocol_fake_env: "
        "the fake marker env (no simulator), the request/response cost alone",
        "steps": args.steps,
        "rounds": args.rounds,
        "render_backend": backend,
        "server_start_s": start_s,
        "identical": identical,
        "per_step": rows,
        "machine": machine_record(),
        "targets": {"overhead_ms": 1.0, "overhead_pct_of_rendered_step": 5.0},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
