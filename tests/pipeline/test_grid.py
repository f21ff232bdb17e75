"""Grid expansion: zipped within a group, crossed across groups, readable cell names."""

from __future__ import annotations

import math

import pytest

from pipeline.grid import expand_grid


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
        ([{"mode": ["Z"]}], r"grid cell \{'mode': 'Z'\}: IDRConfig.mode='Z' is unknown"),
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
