"""tau calibration: the mean E_img of the diagnose cell, then the calibrated cells run with it."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.planning.grid import expand_grid
from pipeline.results.calibration import calibrate
from pipeline.results.store import KEY, RunStore
from tests.doubles.rows import result as hand_made

CONF = Path(__file__).resolve().parents[3] / "conf"


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


def _hand_store(tmp_path: Path) -> tuple[RunStore, dict[str, list[tuple[float, float]]]]:
    """A diagnose cell over two suites with known (E_img, E_prop) per inference."""
    effects = {
        "libero_spatial": [(1.0, 4.0), (3.0, 2.0), (5.0, 0.0)],
        "libero_10": [(10.0, 1.0), (20.0, 3.0)],
    }
    results = []
    for i, (suite, rows) in enumerate(effects.items()):
        episode = {
            "run_id": "r",
            "cell_id": "diagnose",
            "backbone": "lerobot",
            "suite": suite,
            "task_id": f"{suite}/0",
            "episode_index": i,
            "success": True,
            "steps": 10,
        }
        steps = [
            {**{k: episode[k] for k in KEY}, "run_id": "r", "inference_index": k, "step": 2 * k}
            | {"e_img": e_img, "e_prop": e_prop}
            for k, (e_img, e_prop) in enumerate(rows)
        ]
        results.append(hand_made(episode, steps))
    store = RunStore(tmp_path / "run")
    store.write(results)
    return store, effects


def test_calibration_per_suite_equals_the_hand_computed_statistics(tmp_path) -> None:
    store, effects = _hand_store(tmp_path)
    cells = expand_grid(
        [
            {"mode": ["diagnose", "E", "E"], "tau": ["calibrated", "calibrated", "calibrated*2"]},
            {"guidance": ["visual", "proprio"]},
        ]
    ) + expand_grid([{"mode": ["E"], "tau": ["calibrated_q50"]}])
    by_id = {c.cell_id: c for c in cells}
    assert set(by_id) >= {"E_taucal_gvisual", "E_taucal_gproprio", "E_taucalx2_gvisual"}
    result = calibrate(store, cells)
    taus = {cid: c["tau"] for cid, c in result["cells"].items()}
    img = {s: np.array([r[0] for r in rows]) for s, rows in effects.items()}
    prop = {s: np.array([r[1] for r in rows]) for s, rows in effects.items()}
    for suite in effects:  # one tau per suite (per backbone x suite: one backbone per run)
        assert taus["E_taucal_gvisual"][suite] == pytest.approx(img[suite].mean())
        assert taus["E_taucalx2_gvisual"][suite] == pytest.approx(2 * img[suite].mean())
        # proprio guidance gates on E_prop, so its tau is the mean E_prop
        assert taus["E_taucal_gproprio"][suite] == pytest.approx(prop[suite].mean())
        assert taus["E_taucalq50"][suite] == pytest.approx(np.median(img[suite]))
    assert taus["E_taucal_gvisual"] == {"libero_10": 15.0, "libero_spatial": 3.0}
    groups = {g["suite"]: g for g in result["groups"]}
    assert groups["libero_10"]["inferences"] == 2 and groups["libero_10"]["backbone"] == "lerobot"
    # the pooled mean of the first diagnose cell, kept for MLflow's tau_calibrated
    assert result["tau"] == pytest.approx(np.concatenate(list(img.values())).mean())
    assert (
        json.loads((tmp_path / "run" / "calibration.json").read_text())["cells"] == result["cells"]
    )


def test_multiples_and_percentiles_run_end_to_end(tmp_path) -> None:
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.kind=inline",
            "tracking.enabled=false",
            "episodes_per_task=1",
            "grid=[{mode: [diagnose, E]}, {tau: [calibrated*2, calibrated_q90]}]",
        ],
    )
    summary = execute(plan_run(cfg, tmp_path / "run"))
    assert summary.errors == 0
    steps = RunStore(tmp_path / "run").steps().to_pandas()
    e_img = steps.loc[steps.cell_id == "diagnose", "e_img"].astype(float).to_numpy()
    expected = {"E_taucalx2": 2 * e_img.mean(), "E_taucalq90": np.percentile(e_img, 90)}
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    for cell, tau in expected.items():
        assert eps.loc[eps.cell_id == cell, "tau"].to_numpy() == pytest.approx(tau)
        s = steps[steps.cell_id == cell]
        assert ((s.e_img < tau) == (s.gate == 1.0)).all()


def test_calibrated_cell_without_a_diagnose_cell_of_its_intervention_is_refused() -> None:
    with pytest.raises(
        ConfigError,
        match=r"cell 'E_ivmean' has tau: calibrated\*2 but no diagnose cell measures its "
        r"intervention \(strategy=mean.*put mode diagnose in a group crossed with",
    ):
        load_config(
            CONF / "smoke.yaml",
            ["grid=[{mode: [diagnose, E], strategy: [zero, mean]}]", "idr.tau=calibrated*2"],
        )
    with pytest.raises(ConfigError, match=r"idr.tau: tau='calibrate' is not a number or a calibr"):
        load_config(CONF / "smoke.yaml", ["idr.tau=calibrate"])
