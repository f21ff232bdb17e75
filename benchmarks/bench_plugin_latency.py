"""Per-chunk latency of the lerobot policy type ``idr`` against its base, on this machine.

What a robot's control loop waits for at each chunk boundary: the preprocessor, the policy's
``predict_action_chunk`` and the postprocessor, for the base alone (an IDR folder in mode
``baseline``, which is the base's own code path) and for IDR (modes ``diagnose`` and ``E``:
three rows per observation in one forward, unnormalization and refinement). Backbones: lerobot
ACT at its default size built offline from its config (96 px, random weights: the cost is the
same), the project's tiny VLA checkpoint, and learned zoo checkpoints trained by lerobot-train
(``checkpoints/zoo/tiny_vla``, shipped; ACT on MetaWorld, ``checkpoints/zoo/metaworld/act``,
rebuilt by its command in ``checkpoints/zoo/metaworld/REBUILD.json`` and recorded as skipped
where absent). Variants are interleaved round by round so load on the machine hits them alike;
compare the ratios, measured in one run.

Writes ``benchmarks/results/plugin_latency.json`` and prints a table.
Usage: ``python benchmarks/bench_plugin_latency.py [--rounds 30] [--out PATH]``
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch
from lerobot_policy_idr.loading import load_idr
from lerobot_policy_idr.wrap import main as wrap_main

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a plain script: the test fixtures build the ACT base
    sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results" / "plugin_latency.json"
MODES = ("baseline", "diagnose", "E")


def _obs(base: Path) -> dict[str, Any]:
    cfg = json.loads((base / "config.json").read_text())
    g = torch.Generator().manual_seed(0)
    obs: dict[str, Any] = {"task": ["pick up the red cube"]}
    for key, feat in cfg["input_features"].items():
        obs[key] = torch.rand(1, *feat["shape"], generator=g)
    return obs


def measure(name: str, base: Path, work: Path, rounds: int, warmup: int = 3) -> dict[str, Any]:
    loaded = {}
    for mode in MODES:
        folder = work / f"{name}_{mode}"
        args = [
            str(base),
            str(folder),
            "--mode",
            mode,
            "--diagnostics-dir",
            str(work / name / "diag"),
        ]
        assert wrap_main([*args, *(["--tau", "1e9"] if mode == "E" else [])]) == 0
        loaded[mode] = load_idr(folder)
    obs = _obs(base)
    times: dict[str, list[float]] = {m: [] for m in MODES}
    forward: dict[str, list[float]] = {m: [] for m in MODES}
    for r in range(warmup + rounds):
        for mode, (policy, pre, post) in loaded.items():
            policy.reset()
            t0 = time.perf_counter()
            with torch.inference_mode():
                post(policy.predict_action_chunk(pre(dict(obs))))
            if r >= warmup:
                times[mode].append((time.perf_counter() - t0) * 1e3)
    for policy, _, _ in loaded.values():
        policy.sidecar.flush()
    from idr_core.sidecar import read_sidecar

    rows = read_sidecar(work / name / "diag")
    for mode in MODES:
        sel = rows[rows["mode"] == mode]["forward_ms"].to_numpy()[warmup:]
        forward[mode] = [float(x) for x in sel]
    med = {m: statistics.median(v) for m, v in times.items()}
    return {
        "median_ms": med,
        "p90_ms": {m: sorted(v)[int(0.9 * (len(v) - 1))] for m, v in times.items()},
        "forward_median_ms": {m: statistics.median(v) for m, v in forward.items() if v},
        "ratio_E_vs_baseline": med["E"] / med["baseline"],
        "ratio_diagnose_vs_baseline": med["diagnose"] / med["baseline"],
        "rounds": rounds,
    }


def main() -> None:
    from training.toy_checkpoints import build_act

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    results: dict[str, Any] = {
        "what": "per-chunk latency: preprocessor + predict_action_chunk + postprocessor, batch 1",
        "machine": {
            **machine_record(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "device": "cpu",
        },
        "backbones": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        bases = {
            "tiny_vla": ROOT / "checkpoints" / "tiny_vla",
            "zoo_tiny_vla": ROOT / "checkpoints" / "zoo" / "tiny_vla",
        }
        zoo_act = ROOT / "checkpoints" / "zoo" / "metaworld" / "act"
        if (zoo_act / "model.safetensors").is_file():
            bases["zoo_act_metaworld"] = zoo_act
        else:
            results["skipped"] = {
                "zoo_act_metaworld": f"{zoo_act} absent (checkpoints/zoo/metaworld/REBUILD.json)"
            }
        # ACT at lerobot's default widths (dim_model 512, 4+1 layers, ResNet-18), 96 px
        bases["act_96px"] = build_act(
            work / "act_96px", image=96, chunk=100, n_action_steps=100, full_size=True
        )
        for name, base in bases.items():
            results["backbones"][name] = measure(name, base, work, args.rounds)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"{'backbone':<10} {'baseline ms':>12} {'diagnose ms':>12} {'E ms':>8} {'E/base':>7}")
    for name, r in results["backbones"].items():
        m = r["median_ms"]
        print(
            f"{name:<10} {m['baseline']:>12.2f} {m['diagnose']:>12.2f} {m['E']:>8.2f} "
            f"{r['ratio_E_vs_baseline']:>7.2f}"
        )
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
