"""tau calibration: the mean E_img of the diagnose cell, then the calibrated cells run with it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.config import ConfigError, load_config
from pipeline.runner import execute, plan_run
from pipeline.store import RunStore

CONF = Path(__file__).resolve().parents[2] / "conf"


def test_calibrated_tau_is_the_diagnose_mean_and_is_used(tmp_path) -> None:
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.kind=inline",
            "tracking.enabled=false",
            "grid=[{mode: [diagnose, E, F]}]",
            "idr.tau=calibrated",
        ],
    )
    plan = plan_run(cfg, tmp_path / "run")
    assert {s.cell_id for s in plan.specs} == {"diagnose"}
    assert {s.cell_id for s in plan.calibrated} == {"E", "F"}
    summary = execute(plan)
    assert summary.stored == 18 and summary.errors == 0
    store = RunStore(tmp_path / "run")
    steps = store.steps().to_pandas()
    by_hand = steps.loc[steps.cell_id == "diagnose", "e_img"].astype(float).mean()
    saved = json.loads((tmp_path / "run" / "calibration.json").read_text())
    assert saved["tau"] == pytest.approx(by_hand, rel=1e-6)
    assert saved["inferences"] == int((steps.cell_id == "diagnose").sum())
    eps = store.episodes().to_pandas()
    assert eps.loc[eps.cell_id.isin(["E", "F"]), "tau"].eq(saved["tau"]).all()
    # the gate follows the calibrated tau: E's gate opens on inferences with E_img < tau
    e_steps = steps[steps.cell_id == "E"]
    assert ((e_steps.e_img < saved["tau"]) == (e_steps.gate == 1.0)).all()
    # resume: nothing reruns, calibration is recomputed from the same stored steps
    again = execute(plan_run(cfg, tmp_path / "run"))
    assert again.stored == 0 and again.skipped == 18


def test_calibrated_without_diagnose_cell_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"tau: calibrated needs a diagnose cell"):
        load_config(CONF / "smoke.yaml", ["grid=[{mode: [baseline, E]}]", "idr.tau=calibrated"])
