"""The methods table, checked by value on a hand-made run: success, the pairings against the
reference and E, and the cost per executed env step from the step rows."""

from __future__ import annotations

import pytest

from pipeline.reporting.markdown import build_report
from pipeline.reporting.methods import method_costs, methods_table
from pipeline.results.store import RunStore
from tests.doubles.rows import result

# per cell: successes over 6 episodes, and each inference's (pass_rows, executed_steps, ms)
CELLS = {
    "baseline": ([1, 1, 0, 1, 0, 1], (1, 4, 10.0)),
    "E": ([1, 1, 1, 1, 0, 1], (3, 4, 24.0)),
    "random": ([0, 1, 0, 0, 0, 1], (3, 4, 26.0)),
    "temporal": ([1, 1, 1, 1, 1, 1], (1, 1, 9.0)),
}
INFERENCES = 5  # per episode


def _write(run_dir) -> RunStore:
    store = RunStore(run_dir)
    results = []
    for cell, (wins, (rows, executed, ms)) in CELLS.items():
        for i, won in enumerate(wins):
            steps = [
                dict(
                    cell_id=cell,
                    episode_index=i,
                    inference_index=k,
                    step=k * executed,
                    inference_ms=ms,
                    pass_rows=rows,
                    executed_steps=executed,
                )
                for k in range(INFERENCES)
            ]
            episode = dict(cell_id=cell, mode=cell, episode_index=i, success=bool(won), steps=5)
            results.append(result(episode, steps))
    store.write(results)
    return store


def test_methods_table_pairs_each_method_and_prices_it_per_env_step(tmp_path) -> None:
    store = _write(tmp_path)
    episodes = store.episodes().to_pandas()
    costs = method_costs(store.steps())
    for cell, (_, (rows, executed, ms)) in CELLS.items():
        assert costs.loc[cell, "rows_per_step"] == pytest.approx(rows / executed)
        assert costs.loc[cell, "ms_per_step"] == pytest.approx(ms / executed)
    _title, headers, table = methods_table(episodes, store.steps())
    by_cell = {r[2]: dict(zip(headers, r, strict=True)) for r in table}
    assert list(by_cell) == ["baseline", "E", "random", "temporal"]  # the reference first
    assert by_cell["E"]["success % [95% CI]"].startswith("83.3 ")
    # random: 2 of 6 against baseline's 4 of 6 and E's 5 of 6, on the same keys
    assert by_cell["random"]["Δ vs baseline pp [95% CI], p"].startswith("-33.3 ")
    assert by_cell["random"]["Δ vs E pp [95% CI], p"].startswith("-50.0 ")
    assert by_cell["E"]["Δ vs E pp [95% CI], p"] == "–"
    assert "MDE" in by_cell["random"]["Δ vs E pp [95% CI], p"]
    assert by_cell["temporal"]["rows / env step"] == "1.00"
    assert by_cell["E"]["rows / env step"] == "0.75"
    assert "## Test-time methods side by side" in build_report(tmp_path)


def test_a_run_of_one_method_beside_its_reference_has_no_methods_table(tmp_path) -> None:
    store = RunStore(tmp_path)
    store.write(
        [
            result(dict(cell_id=c, mode=c, episode_index=i, success=True))
            for c in ("diagnose", "E")
            for i in range(2)
        ]
    )
    assert methods_table(store.episodes().to_pandas(), store.steps()) is None


def test_a_dose_response_pairs_each_placebo_with_e_of_its_own_alpha(tmp_path) -> None:
    from pipeline.reporting.methods import pairings_vs_e

    wins = {
        ("E_a0.04", "E", 0.04): [1, 1, 1, 1],
        ("E_a0.16", "E", 0.16): [0, 0, 0, 0],
        ("random_a0.04", "random", 0.04): [1, 1, 0, 0],
        ("random_a0.16", "random", 0.16): [1, 1, 0, 0],
    }
    store = RunStore(tmp_path)
    store.write(
        [
            result(dict(cell_id=c, mode=m, alpha=a, episode_index=i, success=bool(w)))
            for (c, m, a), ws in wins.items()
            for i, w in enumerate(ws)
        ]
    )
    pairs = pairings_vs_e(store.episodes().to_pandas())
    assert pairs["random_a0.04"].diff == pytest.approx(-0.5)  # against E at 0.04
    assert pairs["random_a0.16"].diff == pytest.approx(+0.5)  # against E at 0.16
