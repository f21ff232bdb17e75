"""Where a benchmark writes its JSON: the committed results file for a measurement, a fresh
temporary folder for a trial run (``--dry``, ``--quick``, ``--tiny``: toy sizes, seconds on a
CPU), unless ``--out`` names a path.

A trial's figures are not the machine's: written over ``benchmarks/results/<name>.json`` they
would replace a device's measurement in the docs' tables and be committed as one.
"""

from __future__ import annotations

import tempfile
from pathlib import Path


def results_path(committed: Path, out: Path | None, trial: str | None = None) -> Path:
    """``out`` when given; else ``committed`` for a measurement, and for a trial run (``trial``:
    the flag that asked for it, e.g. ``"--dry"``) ``<temp dir>/<name>-<flag>-XXXX/<name>.json``,
    a new folder each run, said on stdout."""
    if out is not None:
        return out
    if not trial:
        return committed
    folder = tempfile.mkdtemp(prefix=f"{committed.stem}-{trial.lstrip('-')}-")
    path = Path(folder) / committed.name
    print(f"{trial} without --out: writing {path} (not {committed})", flush=True)
    return path
