"""A run's tables as hashes: one per episode (its episode row and its step rows) and one for the
whole run, over the columns that results are made of (not timing, placement, run id, code
version or the hardware label). Two run dirs with equal digests hold the same results bit for
bit; where they differ, the per-episode hashes name the first episode that does.

Used by the portable numerics mode's cross-machine check (``benchmarks/bench_portable.py``
writes the reference; ``tests/pipeline/results/test_portable_digest.py`` compares)."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.results.store import EPISODE_SCHEMA, STEP_SCHEMA, RunStore

#: columns that differ between two executions of the same plan by design, or name the machine
EXCLUDED = frozenset(
    {
        "run_id",
        "code_version",
        "wall_seconds",
        "started_at",
        "finished_at",
        "worker",
        "node",
        "inference_ms",
        "inference_ms_mean",
        "attempt",
        "hardware",
    }
)
EPISODE_KEY = ("cell_id", "task_id", "episode_index")


def _plain(v: Any) -> Any:
    """A JSON value that keeps every bit of a float (its hex form) and orders lists."""
    if hasattr(v, "tolist"):
        v = v.tolist()
    if isinstance(v, list | tuple):
        return [_plain(x) for x in v]
    if isinstance(v, float):
        return None if math.isnan(v) else v.hex()
    if v is None or isinstance(v, bool | int | str):
        return v
    return str(v)


def _row_hash(row: dict[str, Any]) -> str:
    text = json.dumps({k: _plain(row[k]) for k in sorted(row)}, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()


def hashed_columns() -> dict[str, list[str]]:
    """The columns ``episode_hashes`` covers by default: every column of the tables' schemas
    (a run dir is always read under them) but the excluded ones. A reference records them, so
    that a column added to the schema later does not change what its hashes compare."""
    return {
        "episodes": [c for c in EPISODE_SCHEMA.names if c not in EXCLUDED],
        "steps": [c for c in STEP_SCHEMA.names if c not in EXCLUDED],
    }


def episode_hashes(
    run_dir: str | Path, columns: dict[str, list[str]] | None = None
) -> dict[str, str]:
    """``cell/task/episode`` -> the hash of that episode's row and its step rows, over
    ``columns`` (``{"episodes": [...], "steps": [...]}``; default: ``hashed_columns``). A
    named column the run lacks is refused: the hashes could not be compared."""
    store = RunStore(Path(run_dir), read_only=True)
    episodes = store.episodes().to_pandas()
    steps = store.steps().to_pandas()
    keep = columns or hashed_columns()
    keep_e, keep_s = list(keep["episodes"]), list(keep["steps"])
    for name, table, cols in (("episodes", episodes, keep_e), ("steps", steps, keep_s)):
        missing = [c for c in cols if c not in table.columns]
        if missing:
            raise ValueError(f"{run_dir}: the {name} table has no column(s) {missing} to hash")
    steps = steps.sort_values([*EPISODE_KEY, "inference_index"])
    by_episode = {k: g for k, g in steps.groupby(list(EPISODE_KEY), sort=False)}
    out = {}
    for _, row in episodes.sort_values(list(EPISODE_KEY)).iterrows():
        key = tuple(row[k] for k in EPISODE_KEY)
        parts = [_row_hash({c: row[c] for c in keep_e})]
        group = by_episode.get(key, pd.DataFrame(columns=keep_s))
        parts += [_row_hash(r) for r in group[keep_s].to_dict("records")]
        out["/".join(str(k) for k in key)] = hashlib.sha256("".join(parts).encode()).hexdigest()
    return out


def run_digest(hashes: dict[str, str]) -> str:
    return hashlib.sha256(
        "".join(f"{k}={hashes[k]}\n" for k in sorted(hashes)).encode()
    ).hexdigest()


def first_difference(ours: dict[str, str], reference: dict[str, str]) -> str | None:
    """The first episode (in key order) whose hash differs or that one side lacks; None: equal."""
    for key in sorted(set(ours) | set(reference)):
        if ours.get(key) != reference.get(key):
            if key not in ours:
                return f"{key}: missing here"
            if key not in reference:
                return f"{key}: not in the reference"
            return f"{key}: differs"
    return None
