"""How far the default's headline moves when only the numerics change, set against how far
sampling alone moves it.

Runs ``conf/default.yaml`` in full (its 20 episodes per task, tracking off), each time in a
fresh ``idr-eval run`` process, under several instruction-set pins of the libraries that pick
kernels by instruction set (torch's ATen, MKL, oneDNN and llvmpipe's shaders):

* ``native``: nothing pinned, what ``make run`` does;
* ``portable``: ``executor.numerics_mode=portable`` (workers/hardware.py ``PORTABLE_ENV``);
* ``torch_scalar``: ``ATEN_CPU_CAPABILITY=default`` only (torch's non-vectorized kernels);
* ``all_scalar``: torch's scalar kernels, MKL's compatible path, oneDNN at SSE4.1 and llvmpipe
  at 128-bit vectors.

Environment pins reach the run's Ray actors through the process environment; every row records
the hardware class its actor saw, and the JSON lists them per pin so a pin that did not take
is visible. For each pin: the headline (E minus diagnose, paired over the same episodes: the
mean difference, its bootstrap 95% interval and McNemar's exact p), success per cell, and how
many episode rows are bit-identical to the native run's. The summary sets the spread of the
headline across pins against the width of one run's sampling interval.

Writes ``benchmarks/results/isa_spread.json``; the native run also re-measures the default's
table for the benchmarks page (``--default-run`` writes its throughput into
``benchmarks/results/default_run.json``'s ``run`` entry).

Usage: ``python benchmarks/bench_isa_spread.py [--pins native,portable,...] [--keep DIR]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "isa_spread.json"
CONFIG = "conf/default.yaml"

SCALAR = {
    "ATEN_CPU_CAPABILITY": "default",
    "MKL_CBWR": "COMPATIBLE",
    "ONEDNN_MAX_CPU_ISA": "SSE41",
    "LP_NATIVE_VECTOR_WIDTH": "128",
}
#: name -> (environment set for the run, config overrides)
PINS: dict[str, tuple[dict[str, str], list[str]]] = {
    "native": ({}, []),
    "portable": ({}, ["executor.numerics_mode=portable"]),
    "torch_scalar": ({"ATEN_CPU_CAPABILITY": "default"}, []),
    "all_scalar": (SCALAR, []),
}


def run(out: Path, env: dict[str, str], overrides: list[str]) -> dict[str, float]:
    """One ``idr-eval run`` of the default in its own process; wall seconds and load."""
    cmd = [
        str(Path(sys.executable).with_name("idr-eval")),
        "run",
        CONFIG,
        "--out",
        str(out),
        "tracking.enabled=false",
        *overrides,
    ]
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    subprocess.run(
        cmd, cwd=ROOT, check=True, capture_output=True, text=True, env={**os.environ, **env}
    )
    return {
        "wall_seconds": round(time.perf_counter() - t0, 1),
        "load_average_at_start": round(load, 2),
    }


def summarize(run_dir: Path) -> dict[str, Any]:
    from pipeline.results import aggregate as agg
    from pipeline.results.store import RunStore

    eps = RunStore(run_dir, read_only=True).episodes().to_pandas()
    ok = eps[eps["error"].isna()]
    success = ok.groupby("cell_id")["success"].mean()
    (paired,) = agg.paired_vs_baseline(eps)
    return {
        "episodes": len(eps),
        "errors": int(eps["error"].notna().sum()),
        "step_rows": int(ok["steps"].sum()),
        "success_by_cell": {k: round(float(v), 4) for k, v in success.items()},
        "headline": dataclasses.asdict(paired),
        "hardware_seen": sorted(set(eps["hardware"].dropna().astype(str))),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pins", default=",".join(PINS), help=f"a subset of {list(PINS)}")
    ap.add_argument("--keep", type=Path, help="keep the run dirs here")
    ap.add_argument(
        "--episodes", type=int, help="episodes per task (default: the config's; a quick check)"
    )
    ap.add_argument(
        "--default-run", action="store_true", help="update default_run.json from the native run"
    )
    args = ap.parse_args()
    names = [p for p in args.pins.split(",") if p]
    unknown = sorted(set(names) - set(PINS))
    if unknown or "native" not in names:
        raise SystemExit(f"--pins: {unknown or 'native missing'}; choose from {list(PINS)}")
    from pipeline.results.digest import episode_hashes
    from workers.hardware import machine_record

    with tempfile.TemporaryDirectory() as tmp:
        base = args.keep or Path(tmp)
        rows: dict[str, dict[str, Any]] = {}
        hashes: dict[str, dict[str, str]] = {}
        for name in names:
            env, overrides = PINS[name]
            out = base / name
            if args.episodes:
                overrides = [*overrides, f"episodes_per_task={args.episodes}"]
            timing = run(out, env, overrides)
            rows[name] = {"env": env, "overrides": overrides, **timing, **summarize(out)}
            hashes[name] = episode_hashes(out)
            print(name, json.dumps(rows[name]["headline"]), flush=True)
        if args.default_run:
            # this script's folder is on sys.path when it runs as a script
            from bench_default_run import RESULTS as DEFAULT
            from bench_default_run import run_dir_throughput

            doc = json.loads(DEFAULT.read_text())
            doc["run"] = run_dir_throughput(base / "native")
            doc["machine"] = machine_record()
            DEFAULT.write_text(json.dumps(doc, indent=1) + "\n")
    native = hashes["native"]
    for name in names:
        rows[name]["rows_identical_to_native"] = sum(
            native.get(k) == v for k, v in hashes[name].items()
        )
    diffs = [rows[n]["headline"]["diff"] for n in names]
    widths = [rows[n]["headline"]["ci_high"] - rows[n]["headline"]["ci_low"] for n in names]
    spread, width = max(diffs) - min(diffs), sum(widths) / len(widths)
    result = {
        "config": CONFIG,
        "overrides": ["tracking.enabled=false"]
        + ([f"episodes_per_task={args.episodes}"] if args.episodes else []),
        "machine": machine_record(),
        "date": date.today().isoformat(),
        "pins": rows,
        "summary": {
            "headline_min": min(diffs),
            "headline_max": max(diffs),
            "headline_spread": round(spread, 4),
            "ci_width_mean": round(width, 4),
            "spread_over_ci_width": round(spread / width, 3) if width > 0 else None,
            "p_values": {n: rows[n]["headline"]["p_value"] for n in names},
        },
    }
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result["summary"], indent=2))


if __name__ == "__main__":
    main()
