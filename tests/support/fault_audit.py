"""What a fault test measures in a RUN_DIR: episodes lost or duplicated, unreadable or
leftover files. Every fault test asserts these are all zero and records them for the report
(benchmarks/fault_report.py -> benchmarks/results/faults.json)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq

from pipeline.results.store import EPISODE_SCHEMA, KEY


def audit(run_dir: Path, expected: set[tuple[str, str, int]]) -> dict[str, Any]:
    """Read every Parquet file of ``run_dir`` and compare its episode keys to ``expected``."""
    run_dir = Path(run_dir)
    unreadable, keys = 0, Counter()
    for f in sorted(run_dir.glob("*/cell=*/*.parquet")):
        try:
            table = pq.read_table(f)
        except Exception:
            unreadable += 1
            continue
        if f.relative_to(run_dir).parts[0] == "episodes":
            t = table.select(list(KEY)).to_pydict()
            keys.update(zip(t["cell_id"], t["task_id"], t["episode_index"], strict=True))
    episodes = {
        p.relative_to(run_dir / "episodes") for p in run_dir.glob("episodes/cell=*/*.parquet")
    }
    orphans = [
        p
        for p in run_dir.glob("steps/cell=*/*.parquet")
        if p.relative_to(run_dir / "steps") not in episodes
    ]
    temps = list(run_dir.rglob("*.tmp"))
    errors = 0
    for f in run_dir.glob("episodes/cell=*/*.parquet"):
        col = pq.read_table(f, schema=EPISODE_SCHEMA, columns=["error"]).column("error")
        errors += len(col) - col.null_count
    return {
        "expected": len(expected),
        "stored": sum(keys.values()),
        "lost": len(expected - set(keys)),
        "duplicated": sum(c - 1 for c in keys.values() if c > 1),
        "unexpected": len(set(keys) - expected),
        "unreadable_files": unreadable,
        "temp_files_left": len(temps),
        "orphan_step_files": len(orphans),
        "error_rows": errors,
    }


def assert_clean(outcome: dict[str, Any], *, complete: bool = True) -> None:
    """Nothing lost (when the run is ``complete``), duplicated, unreadable or left over."""
    bad = {
        k: outcome[k]
        for k in (
            "duplicated",
            "unexpected",
            "unreadable_files",
            "temp_files_left",
            "orphan_step_files",
        )
        if outcome[k]
    }
    if complete and outcome["lost"]:
        bad["lost"] = outcome["lost"]
    assert not bad, f"run dir not clean: {bad} ({outcome})"
