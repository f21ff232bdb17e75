"""The fault table: run the fault tests, collect what each measured, write and print it.

Every fault test injects its fault for real (a hung call, NaN from a backbone, a diverging
MuJoCo simulation, SIGTERM / SIGINT / SIGKILL to the driver, a full tmpfs, an allocation
past RLIMIT_AS, a killed or crashing actor, fuzzed configs, hostile paths and pickles) and
records its outcome: episodes lost or duplicated, unreadable or left-over files.

Writes ``benchmarks/results/faults.json`` and prints its table (docs/guarantees.md renders it
from the JSON). Usage: ``python benchmarks/fault_report.py`` (about 5 minutes on 2 cores).
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "faults.json"
TESTS = [
    *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "tests/pipeline").glob("test_faults_*.py")),
    "tests/pipeline/execution/test_scheduler.py",  # ray.kill, a crashing actor, SIGKILL to the driver
    "tests/pipeline/execution/test_shared_policy.py",  # a policy actor out of device memory
]
COUNTS = ("lost", "duplicated", "unreadable_files", "temp_files_left", "orphan_step_files")


def table(records: list[dict[str, Any]]) -> str:
    lines = [
        "| fault | how injected | guaranteed | measured: lost / duplicated / unreadable / left over |",
        "|---|---|---|---|",
    ]
    for r in records:
        o = r["outcome"]
        if "lost" in o:
            left = o["temp_files_left"] + o["orphan_step_files"]
            measured = f"{o['lost']} / {o['duplicated']} / {o['unreadable_files']} / {left}"
            measured += (
                f" ({o['stored']} of {o['expected']} keys stored, {o['error_rows']} error rows)"
            )
        else:
            measured = ", ".join(f"{k} {v}" for k, v in o.items())
        lines.append(f"| {r['fault']} | {r['injected']} | {r['guaranteed']} | {measured} |")
    return "\n".join(lines)


def main() -> int:
    with tempfile.TemporaryDirectory() as d:
        target = Path(d) / "records.json"
        env = {**os.environ, "IDR_FAULT_REPORT": str(target)}
        t0 = time.monotonic()
        cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", *TESTS]
        done = subprocess.run(cmd, cwd=ROOT, env=env, check=False)
        wall = time.monotonic() - t0
        records = json.loads(target.read_text()) if target.exists() else []
    totals = {k: sum(r["outcome"].get(k, 0) for r in records) for k in COUNTS}
    report = {
        "generated_at": datetime.now(UTC).isoformat(timespec="seconds"),
        "machine": {**machine_record(), "platform": platform.platform()},
        "command": " ".join(cmd[1:]),
        "pytest_exit_code": done.returncode,
        "wall_seconds": round(wall, 1),
        "totals": totals,
        "faults": records,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(report, indent=2) + "\n")
    print(table(records))
    print(f"\ntotals over {len(records)} faults: {totals}; pytest exit {done.returncode}")
    print(f"wrote {RESULTS.relative_to(ROOT)}")
    return done.returncode or int(any(totals.values()))


if __name__ == "__main__":
    sys.exit(main())
