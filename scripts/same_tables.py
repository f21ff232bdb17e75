"""Whether two run dirs hold the same episode and step tables, volatile columns aside.

Used to show that a change of code leaves results unchanged: run the same config with the old
and the new code into two run dirs, then ``python scripts/same_tables.py OLD NEW``. Rows are
matched on their keys; columns only one side has (a column added since) are listed, not
compared. Exit 0 when every shared column is equal (floats to 1e-9 relative), 1 otherwise.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.dataset as ds

from pipeline.results.digest import EXCLUDED

# what differs between two executions of the same plan by design, or names the machine
VOLATILE = EXCLUDED
KEYS = {
    "episodes": ["cell_id", "task_id", "episode_index"],
    "steps": ["cell_id", "task_id", "episode_index", "inference_index"],
}


def table(run_dir: Path, name: str) -> pd.DataFrame:
    files = sorted(
        str(p) for p in (run_dir / name).rglob("*.parquet") if not p.name.startswith(".")
    )
    df = ds.dataset(files, format="parquet").to_table().to_pandas()
    return df.sort_values(KEYS[name]).reset_index(drop=True)


def same(a: pd.Series, b: pd.Series) -> bool:
    if a.dtype.kind == "f" and b.dtype.kind == "f":
        return bool(np.allclose(a.to_numpy(), b.to_numpy(), rtol=1e-9, atol=0, equal_nan=True))
    return a.astype(str).tolist() == b.astype(str).tolist()


def compare(old: Path, new: Path) -> list[str]:
    problems = []
    for name in KEYS:
        a, b = table(old, name), table(new, name)
        if len(a) != len(b) or a[KEYS[name]].values.tolist() != b[KEYS[name]].values.tolist():
            problems.append(f"{name}: different rows ({len(a)} vs {len(b)})")
            continue
        only = sorted(set(a.columns) ^ set(b.columns))
        if only:
            print(f"{name}: columns on one side only (not compared): {only}")
        shared = [c for c in a.columns if c in b.columns and c not in VOLATILE]
        bad = [c for c in shared if not same(a[c], b[c])]
        problems += [f"{name}.{c} differs" for c in bad]
        print(f"{name}: {len(a)} rows, {len(shared)} columns compared, {len(bad)} differ")
    return problems


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("old", type=Path)
    p.add_argument("new", type=Path)
    args = p.parse_args(argv)
    problems = compare(args.old, args.new)
    for line in problems:
        print(line, file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
