"""Grid expansion: zipped within a group, crossed across groups, readable cell names."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from idr_core.calibration import TauSpec, parse_tau

from pipeline.planning.config import load_config
from pipeline.planning.grid import expand_grid


def test_zip_within_cross_across() -> None:
    cells = expand_grid(
        [{"mode": ["E", "F"]}, {"alpha": [0.05, 0.1, 0.5], "tau": [5, 7, 9]}],
        base={"beta": 0.05},
    )
    assert [c.cell_id for c in cells] == [
        "E_a0.05_tau5",
        "E_a0.1_tau7",
        "E_a0.5_tau9",
        "F_a0.05_tau5",
        "F_a0.1_tau7",
        "F_a0.5_tau9",
    ]
    c = cells[4]
    assert (c.idr.mode, c.idr.alpha, c.idr.tau, c.idr.beta) == ("F", 0.1, 7, 0.05)


def test_baseline_cells_collapse_into_one() -> None:
    cells = expand_grid([{"mode": ["baseline", "E"]}, {"alpha": [0.05, 0.1]}])
    assert [c.cell_id for c in cells] == ["baseline", "E_a0.05", "E_a0.1"]


def test_strategy_and_guidance_names() -> None:
    cells = expand_grid([{"strategy": ["zero", "mean"]}, {"guidance": ["visual", "proprio"]}])
    assert [c.cell_id for c in cells] == [
        "ivzero_gvisual",
        "ivzero_gproprio",
        "ivmean_gvisual",
        "ivmean_gproprio",
    ]
    assert cells[2].intervention.strategy == "mean"


def test_infinite_tau_name() -> None:
    (cell,) = expand_grid([{"tau": [math.inf]}])
    assert cell.cell_id == "tauinf" and cell.idr.tau == math.inf


@pytest.mark.parametrize(
    ("grid", "pattern"),
    [
        ([{"alpha": [0.1, 0.2], "tau": [1]}], r"grid\[0\]: lists in one group .* equal lengths"),
        ([{"alhpa": [0.1]}], r"grid\[0\]: unknown parameter 'alhpa'"),
        ([{"mode": ["Z"]}], r"grid cell \{'mode': 'Z'\}: RefinerConfig.mode='Z' is unknown"),
        ([{"alpha": [-1.0]}], r"alpha=-1.0 must be a number >= 0"),
        ([{"strategy": ["blur"]}], r"intervention.strategy='blur' is unknown"),
        ([{"alpha": []}], r"empty value list"),
        ([{"alpha": [0.1]}, {"alpha": [0.2]}], r"'alpha' appears in groups 0 and 1"),
        ([{"alpha": [0.1, 0.1]}], r"two cells named 'a0.1'"),
    ],
)
def test_bad_grids(grid, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        expand_grid(grid)


# -- calibrated tau forms, diagnose collapse, the paper's ablation presets ------------------------

GRIDS = Path(__file__).resolve().parents[3] / "conf" / "grids"


@pytest.mark.parametrize(
    ("text", "quantile", "scale", "short"),
    [
        ("calibrated", None, 1.0, "cal"),
        ("calibrated*2", None, 2.0, "calx2"),
        ("calibrated*.5", None, 0.5, "calx0.5"),
        ("calibrated_q90", 90.0, 1.0, "calq90"),
        ("calibrated_q97.5*0.5", 97.5, 0.5, "calq97.5x0.5"),
    ],
)
def test_tau_spec_forms(text, quantile, scale, short) -> None:
    spec = parse_tau(text)
    assert isinstance(spec, TauSpec)
    assert (spec.quantile, spec.scale, spec.short) == (quantile, scale, short)
    assert parse_tau(spec.text) == spec  # the spelling round-trips


def test_tau_spec_resolves_mean_multiple_and_percentile() -> None:
    e = np.array([1.0, 2.0, 3.0, 4.0, np.nan])  # a NaN (no diagnostics) is ignored
    assert parse_tau("calibrated").resolve(e) == pytest.approx(2.5)
    assert parse_tau("calibrated*2").resolve(e) == pytest.approx(5.0)
    assert parse_tau("calibrated_q50").resolve(e) == pytest.approx(2.5)
    assert parse_tau("calibrated_q90*0.5").resolve(e) == pytest.approx(0.5 * 3.7)


@pytest.mark.parametrize(
    ("value", "pattern"),
    [
        ("calibrted", r"tau='calibrted' is not a number or a calibrated form; write a number"),
        ("calibrated*0", r"the multiple must be > 0"),
        ("calibrated_q100", r"the percentile must be in \(0, 100\)"),
        ("calibrated*2x", r"not a number or a calibrated form.*e.g. tau: calibrated\*2"),
    ],
)
def test_bad_tau_forms(value, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        expand_grid([{"tau": [value]}])


def test_calibrated_forms_in_cell_ids_and_params() -> None:
    cells = expand_grid(
        [{"mode": ["diagnose", "E"]}, {"tau": ["calibrated*0.5", "calibrated_q90", 999]}]
    )
    assert [c.cell_id for c in cells] == ["diagnose", "E_taucalx0.5", "E_taucalq90", "E_tau999"]
    by_id = {c.cell_id: c for c in cells}
    assert by_id["E_taucalq90"].calibrated_tau == TauSpec(90.0, 1.0)
    assert by_id["E_taucalq90"].params()["tau"] == "calibrated_q90"
    assert by_id["E_tau999"].calibrated_tau is None and by_id["E_tau999"].idr.tau == 999
    assert by_id["diagnose"].calibrated_tau is None  # it measures; it is not calibrated
    assert by_id["E_taucalx0.5"].calibration_source(cells) is by_id["diagnose"]


def test_diagnose_cells_collapse_but_keep_the_intervention() -> None:
    cells = expand_grid(
        [{"mode": ["diagnose", "E"]}, {"alpha": [0.05, 0.1]}, {"strategy": ["zero", "mean"]}]
    )
    assert [c.cell_id for c in cells] == [
        "diagnose_ivzero",
        "diagnose_ivmean",
        "E_a0.05_ivzero",
        "E_a0.05_ivmean",
        "E_a0.1_ivzero",
        "E_a0.1_ivmean",
    ]
    e_mean = cells[3]
    assert e_mean.calibration_source(cells).cell_id == "diagnose_ivmean"


@pytest.mark.parametrize(
    ("preset", "cell_ids"),
    [
        (
            "alpha.yaml",
            ["baseline", "diagnose"]
            + [f"E_a{a}" for a in ("0.02", "0.05", "0.08", "0.1", "0.2", "0.5", "1")],
        ),
        (
            "tau.yaml",
            [
                "baseline",
                "diagnose",
                "E_taucalx0.25",
                "E_taucalx0.5",
                "E_taucal",
                "E_taucalx2",
                "E_taucalx4",
                "E_tau999",
            ],
        ),
        (
            "intervention.yaml",
            [
                "baseline",
                "diagnose_ivzero",
                "diagnose_ivmean",
                "diagnose_ivgaussian",
                "E_ivzero",
                "E_ivmean",
                "E_ivgaussian",
            ],
        ),
        ("modes.yaml", ["baseline", "diagnose", "A", "B", "C", "D", "E", "F"]),
        ("guidance.yaml", ["baseline", "diagnose", "E_gvisual", "E_gproprio"]),
    ],
)
def test_ablation_presets_expand_to_the_papers_cells(preset, cell_ids) -> None:
    cfg = load_config(GRIDS / preset)
    cells = cfg.cells()
    assert [c.cell_id for c in cells] == cell_ids
    assert len(cells) <= cfg.max_cells  # runs without --yes
    assert cfg.backbone.kind == "fake_marker" and cfg.env.suite == "fake_marker"
    # every refining cell is calibrated on a diagnose cell of its own intervention, except
    # the fixed numbers of the tau sweep (999: always on)
    for c in cells:
        if c.idr.refines and c.cell_id != "E_tau999":
            assert c.calibrated_tau is not None
            assert c.calibration_source(cells).intervention == c.intervention
    if preset == "alpha.yaml":
        alphas = sorted(c.idr.alpha for c in cells if c.idr.mode == "E")
        assert {0.02, 0.05, 0.08, 0.1, 0.5, 1.0} <= set(alphas)
    if preset == "intervention.yaml":
        assert {c.intervention.strategy for c in cells} == {"zero", "mean", "gaussian"}


def test_presets_point_at_the_tiny_vla_with_overrides() -> None:
    """The overrides written in conf/grids/alpha.yaml give a valid tiny-VLA-on-tabletop config."""
    cfg = load_config(
        GRIDS / "modes.yaml",
        [
            "backbone.kind=lerobot",
            "backbone.params={path: checkpoints/tiny_vla, device: cpu}",
            "env.suite=tabletop",
            "env.tasks=[pick_color, stack_color, organize]",
            "env.params={image_size: 96, cameras: [agentview, wrist]}",
            "intervention.state_space=normalized",
        ],
    )
    assert cfg.backbone.params == {"path": "checkpoints/tiny_vla", "device": "cpu"}
    assert [c.cell_id for c in cfg.cells()][-1] == "F"


@pytest.mark.parametrize(
    ("groups", "words"),
    [
        ([{"mode": ["E", "cfg"], "w": [0.1, 0.2]}], r"mode 'E' does not read \['w'\]"),
        ([{"mode": ["cfg"]}, {"alpha": [0.05, 0.1]}], r"mode 'cfg' does not read \['alpha'\]"),
        ([{"mode": ["temporal"], "horizon": [2]}], r"mode 'temporal' does not read \['horizon'\]"),
        ([{"mode": ["diagnose"], "samples": [4]}], r"mode 'diagnose' does not read \['samples'\]"),
    ],
)
def test_a_method_setting_on_an_axis_its_mode_ignores_is_refused(groups, words) -> None:
    with pytest.raises(ValueError, match=words):
        expand_grid(groups)


def test_method_settings_name_their_cells_and_horizon_splits_the_baseline() -> None:
    cells = expand_grid(
        [{"mode": ["baseline", "baseline", "cfg", "ensemble"], "horizon": [1, 8, 4, 4]}]
    )
    assert [c.cell_id for c in cells] == ["baseline_h1", "baseline_h8", "cfg_h4", "ensemble_h4"]
    assert cells[2].meaningful_params().keys() >= {"mode", "w", "horizon"}
    assert "alpha" not in cells[2].meaningful_params() and "tau" not in cells[3].meaningful_params()
    assert [c.role for c in expand_grid([{"mode": ["random", "pcd", "F"]}])] == [
        "control",
        "method",
        "idr",
    ]
