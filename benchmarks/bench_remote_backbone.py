"""The remote backbone's cost per inference over loopback: IDR's three passes as one batched
request vs three requests, against the same closed-form policy called in this process.

The server is the fake openpi-protocol server (``workers.backbones.websocket.fake_server``,
another process, websockets); the in-process reference is its policy as a backbone
(``workers.backbones.websocket.fake_backbone``) on the same observations.
Writes ``benchmarks/results/remote_backbone.json``.
Usage: ``python benchmarks/bench_remote_backbone.py [--calls 300]``
"""

from __future__ import annotations

import argparse
import json
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = Path(__file__).parent / "results" / "remote_backbone.json"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def measure(policy: Any, obs: Any, calls: int) -> float:
    from idr_core.refiner import RefinerConfig

    cfg = RefinerConfig(mode="E")
    policy.infer(obs, 0, cfg)
    times = []
    for i in range(calls):
        t0 = time.perf_counter()
        policy.infer(obs, i, cfg)
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=300)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    from workers.backbones.websocket.client import WebsocketBackbone
    from workers.backbones.websocket.fake_backbone import KEY_MAP, ClosedFormBackbone
    from workers.episode.observation import to_policy_observation
    from workers.policy.wrapper import IDRWrapper

    rng = np.random.default_rng(0)
    from workers.envs.base import EnvObservation

    raw = EnvObservation(
        images={"agentview": rng.integers(0, 256, (96, 96, 3), dtype=np.uint8)},
        state=rng.standard_normal(8).astype(np.float32),
    )
    obs = to_policy_observation(raw, "pick up the red cube")
    rows: dict[str, float] = {
        "in_process_ms": measure(IDRWrapper(ClosedFormBackbone()), obs, args.calls)
    }
    for label, flags in (("three_requests_ms", []), ("one_batched_request_ms", ["--batch"])):
        port = _port()
        server = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "workers.backbones.websocket.fake_server",
                "--port",
                str(port),
                *flags,
            ],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            text=True,
        )
        try:
            assert server.stdout is not None and server.stdout.readline().strip() == "ready"
            backbone = WebsocketBackbone(port=port, key_map=KEY_MAP)
            rows[label] = measure(IDRWrapper(backbone), obs, args.calls)
            backbone.close()
        finally:
            server.kill()
            server.wait()
    for k, v in rows.items():
        print(f"{k:<24} {v:6.2f} ms per inference (IDR: 3 passes)")
    out = {
        "what": "IDR inference (mode E, 3 passes) of a closed-form policy: in this process vs "
        "over loopback websockets (openpi's protocol), 96 px image + 8-d state",
        "calls": args.calls,
        "per_inference": rows,
        "machine": machine_record(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
