"""The portable numerics mode on the default slice: identical run to run, what it costs, and
how its tables compare with the host's own kernels; and the reference digest other machines
are checked against.

Runs ``conf/default.yaml`` at ``--episodes`` per task (default 3) three times, each in a fresh
``idr-eval run`` process: portable twice, native once. Writes
``benchmarks/results/portable_numerics.json``: the machine, the wall times, whether the two
portable runs are identical, how many episodes native and portable share bit for bit, and the
portable run's per-episode hashes (``pipeline.results.digest``) and the columns they cover, which
``tests/pipeline/results/test_portable_digest.py`` checks on whatever machine runs it.

A machine's result is added to the file's ``machines`` list (the same CPU model and instruction
set replace their earlier entry): ``holds`` says whether its portable tables equal the
reference's. The first machine to write the file sets the reference; ``--reference`` keeps it
and only adds this machine.

Usage: ``python benchmarks/bench_portable.py [--episodes 3] [--reference]``
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from datetime import date
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "portable_numerics.json"
CONFIG = "conf/default.yaml"


def slice_overrides(episodes: int) -> list[str]:
    return [f"episodes_per_task={episodes}", "tracking.enabled=false"]


LOAD: dict[str, float] = {}  # the 1-minute load average when each run started


def run(out: Path, mode: str, episodes: int) -> float:
    cmd = [
        str(Path(sys.executable).with_name("idr-eval")),
        "run",
        CONFIG,
        "--out",
        str(out),
        *slice_overrides(episodes),
        f"executor.numerics_mode={mode}",
    ]
    import os

    LOAD[f"{out.name}"] = round(os.getloadavg()[0], 2)
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=ROOT, check=True, capture_output=True, text=True)
    return time.perf_counter() - t0


def machine() -> dict[str, str]:
    from workers.hardware import machine_record

    return machine_record()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=3)
    ap.add_argument("--reference", action="store_true", help="keep the file's reference")
    args = ap.parse_args()
    from pipeline.results.digest import (
        episode_hashes,
        first_difference,
        hashed_columns,
        run_digest,
    )

    old = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    keep = args.reference and old.get("hashes")
    with tempfile.TemporaryDirectory() as tmp:
        t = Path(tmp)
        wall = {
            "portable_1": run(t / "p1", "portable", args.episodes),
            "portable_2": run(t / "p2", "portable", args.episodes),
            "native": run(t / "n", "native", args.episodes),
        }
        # a kept reference is compared over the columns it hashed, a new one records its own
        columns = old["columns"] if keep else hashed_columns()
        p1, p2, n = (episode_hashes(t / d, columns) for d in ("p1", "p2", "n"))
    same_native = sum(p1[k] == n.get(k) for k in p1)
    reference = old["hashes"] if keep else p1
    here = machine()
    entry = {
        **here,
        "holds": first_difference(p1, reference) is None,
        "first_difference": first_difference(p1, reference),
        "date": date.today().isoformat(),
    }
    machines = [
        m
        for m in old.get("machines", [])
        if (m["cpu_model"], m["cpu_capability"]) != (here["cpu_model"], here["cpu_capability"])
    ] + [entry]
    result = {
        "config": CONFIG,
        "overrides": slice_overrides(args.episodes),
        "episodes": len(p1),
        "digest": run_digest(reference),
        "columns": columns,
        "hashes": reference,
        "machines": machines,
        "measured_on": here,
        "portable_run_to_run_identical": p1 == p2,
        "episodes_equal_native_vs_portable": same_native,
        "wall_seconds": {k: round(v, 1) for k, v in wall.items()},
        # other load on the machine skews the wall times, not the tables
        "load_average_at_start": dict(LOAD),
        "portable_cost_ratio": round(
            (wall["portable_1"] + wall["portable_2"]) / 2 / wall["native"], 3
        ),
    }
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "hashes"}, indent=2))


if __name__ == "__main__":
    main()
