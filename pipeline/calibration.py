"""tau calibration, the paper's rule: tau := mean E_img of the diagnose cell over its steps.

The diagnose cell executes the base action (with shared noise it is also the baseline) and
records E_img at every inference; cells with ``tau: calibrated`` are scheduled after it, with
that mean as their threshold. The value is written to RUN_DIR/calibration.json, logged to
MLflow, and recorded in every episode row (column ``tau``).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pyarrow.compute as pc

from pipeline.store import RunStore

CALIBRATION_FILE = "calibration.json"


def mean_e_img(store: RunStore, cell_id: str) -> tuple[float, int]:
    """Mean E_img over all stored inferences of ``cell_id`` and how many there were."""
    steps = store.steps().select(["cell_id", "e_img"])
    steps = steps.filter(pc.and_(pc.equal(steps["cell_id"], cell_id), pc.is_valid(steps["e_img"])))
    n = steps.num_rows
    if n == 0:
        return math.nan, 0
    return float(pc.mean(steps["e_img"]).as_py()), n


def calibrate(store: RunStore, diagnose_cell: str) -> dict[str, float | int | str]:
    tau, n = mean_e_img(store, diagnose_cell)
    if n == 0 or not math.isfinite(tau):
        raise RuntimeError(
            f"tau calibration: the diagnose cell {diagnose_cell!r} stored no E_img (all its episodes "
            "errored?); see the errors in the report"
        )
    result = {"tau": tau, "inferences": n, "source_cell": diagnose_cell, "rule": "mean E_img"}
    path = Path(store.run_dir) / CALIBRATION_FILE
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    tmp.replace(path)
    return result
