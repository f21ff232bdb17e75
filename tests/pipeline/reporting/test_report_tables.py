"""The report's tables, checked by value: a hand-made run whose numbers are known by hand, its
report parsed back, and every table compared with the aggregation it is built from."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from pipeline.reporting.markdown import TABLES, build_report
from pipeline.results import aggregate as agg
from pipeline.results.store import RunStore
from tests.doubles.rows import result


def _episodes() -> list[dict[str, object]]:
    """Two cells x two suites on the same (task, episode) keys. baseline: s1/pick 2 of 4,
    s2/chain 1 of 2 (a 3-subtask chain); E: s1/pick 4 of 4, s2/chain 2 of 2; one error row."""
    rows: list[dict[str, object]] = []
    pick = {"baseline": [1, 0, 1, 0], "E": [1, 1, 1, 1]}
    for cell, wins in pick.items():
        for i, won in enumerate(wins):
            rows.append(
                dict(
                    cell_id=cell,
                    mode="baseline" if cell == "baseline" else "E",
                    suite="s1",
                    task_id="pick",
                    task_name="pick",
                    episode_index=i,
                    success=bool(won),
                    steps=20 if won else 50,
                    success_step=20 if won else None,
                    max_steps=50,
                    sim_seconds=(20 if won else 50) / 10,
                    wall_seconds=2.0,
                    inference_ms_mean=10.0 if cell == "baseline" else 30.0,
                    failure=None if won else "timeout",
                    e_img_mean=None if cell == "baseline" else 4.0,
                    e_prop_mean=None if cell == "baseline" else 1.0,
                    r_img_mean=None if cell == "baseline" else 0.8,
                    gate_rate=None if cell == "baseline" else 0.25,
                )
            )
    chain = {"baseline": [(3, True), (1, False)], "E": [(3, True), (3, True)]}
    for cell, outcomes in chain.items():
        for i, (done, won) in enumerate(outcomes):
            rows.append(
                dict(
                    cell_id=cell,
                    mode="baseline" if cell == "baseline" else "E",
                    suite="s2",
                    task_id="chain",
                    task_name="chain",
                    episode_index=i,
                    success=won,
                    steps=30,
                    success_step=30 if won else None,
                    max_steps=60,
                    subtasks_total=3,
                    subtasks_done=done,
                    sim_seconds=3.0,
                    wall_seconds=4.0,
                    failure=None if won else "wrong_order",
                )
            )
    rows.append(
        dict(cell_id="E", mode="E", suite="s1", task_id="pick", task_name="pick",
             episode_index=4, error="RuntimeError: boom\ntraceback", attempt=3)
    )  # fmt: skip
    return rows


def _tables(text: str) -> dict[str, pd.DataFrame]:
    """Every ``## title`` section's Markdown table, as strings."""
    out: dict[str, pd.DataFrame] = {}
    title = None
    lines = text.splitlines()
    for i, line in enumerate(lines):
        if line.startswith("## "):
            title = line[3:]
        elif line.startswith("| ") and title is not None and title not in out:
            block = []
            for row in lines[i:]:
                if not row.startswith("|"):
                    break
                block.append([c.strip() for c in row.strip("|").split("|")])
            out[title] = pd.DataFrame(block[2:], columns=block[0])
    return out


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, pd.DataFrame]]:
    run = tmp_path_factory.mktemp("hand") / "run"
    RunStore(run).write(result(r) for r in _episodes())
    return run, _tables(build_report(run))


def test_the_main_table_holds_the_rates_and_the_paired_difference(report) -> None:
    _, tables = report
    main = tables["Success rate (%) by suite, with the paired difference against baseline"]
    row = main.set_index("cell")
    # by hand: baseline s1 2/4 = 50.0, s2 1/2 = 50.0; E s1 4/4, s2 2/2 (its error row excluded)
    assert row.loc["baseline", "s1"] == "50.0" and row.loc["baseline", "s2"] == "50.0"
    assert row.loc["E", "s1"] == "100.0" and row.loc["E", "s2"] == "100.0"
    assert row.loc["E", "errors"] == "1" and row.loc["baseline", "errors"] == "0"
    lo, hi = agg.wilson(3, 6)
    assert row.loc["baseline", "Avg"] == f"50.0 [{100 * lo:.1f}, {100 * hi:.1f}]"
    # E wins 3 pairs the baseline lost and loses none: +50 pp over 6 pairs, McNemar 2 * 0.5^3
    delta = row.loc["E", "Δ vs baseline (95% CI)"]
    assert delta.startswith("+50.0 [") and delta.endswith("(n=6)")
    assert float(row.loc["E", "p (McNemar)"]) == pytest.approx(0.25)
    assert list(main["cell"]) == ["baseline", "E"]  # the reference first


def test_every_table_equals_the_aggregation_it_is_built_from(report) -> None:
    run, tables = report
    text = build_report(run)
    headings = [line for line in text.splitlines() if line.startswith("## ")]
    assert len(headings) == len(set(headings)), headings  # each section once
    for title in tables:  # and each heading followed by its table
        after = text.split(f"## {title}\n", 1)[1].lstrip("\n")
        assert after.startswith("| "), title
    episodes = RunStore(run, read_only=True).episodes().to_pandas()
    for table in TABLES:
        built = table(episodes)
        if built is None:
            continue
        title, headers, rows = built
        got = tables[title]
        assert list(got.columns) == headers, title
        assert got.values.tolist() == [[str(c) for c in r] for r in rows], title
    by_task = tables["Success by task (%, Wilson 95% interval)"].set_index(["cell", "task"])
    assert by_task.loc[("baseline", "pick"), "success"] == "50.0"
    assert by_task.loc[("E", "pick"), "n"] == "4" and by_task.loc[("E", "pick"), "errors"] == "1"
    chains = tables["Chains: i/N completion rates (%) and Avg Len (bootstrap 95%)"]
    chains = chains.set_index("cell")
    # baseline: chains of 3 and 1 subtasks: 1/3 100%, 2/3 and 3/3 50%, Avg Len 2.00
    assert chains.loc["baseline", ["1/3", "2/3", "3/3"]].tolist() == ["100.0", "50.0", "50.0"]
    assert chains.loc["baseline", "Avg Len"].startswith("2.00 [")
    assert chains.loc["E", "Avg Len"].startswith("3.00 [3.00, 3.00]")
    causes = tables["Failures by cause (episodes without success; errors excluded)"]
    causes = causes.set_index(["cell", "task"])
    assert causes.loc[("baseline", "pick"), "timeout"] == "2"
    assert causes.loc[("baseline", "chain"), "wrong_order"] == "1"
    times = tables["Completion time"].set_index(["cell", "suite"])
    assert float(times.loc[("baseline", "s1"), "sim s to success"]) == pytest.approx(2.0)
    assert float(times.loc[("E", "s1"), "inference ms"]) == pytest.approx(30.0)
    diag = tables["Diagnostics (means over episodes)"].set_index("cell")
    assert float(diag.loc["E", "gate rate"]) == pytest.approx(0.25)
    assert float(diag.loc["E", "R_img"]) == pytest.approx(0.8)
    assert diag.loc["baseline", "E_img"] == "–"
    errors = tables["Errors (not counted as failures)"]
    assert errors.values.tolist() == [["E", "pick", "4", "3", "RuntimeError: boom"]]


def test_the_report_names_the_numerical_path_and_warns_when_a_run_mixes_them() -> None:
    from pipeline.reporting.markdown import numerics_lines

    one = pd.DataFrame({"numerics": ["rows=96 threads=1"] * 3, "hardware": ["EPYC / AVX2"] * 3})
    assert numerics_lines(one) == [
        "Numerical path: `rows=96 threads=1` on `EPYC / AVX2` (3 episodes)."
    ]
    mixed = pd.DataFrame(
        {"numerics": ["request threads=1", "rows=96 threads=1", None, "request threads=1"]}
    )
    (line,) = numerics_lines(mixed)  # rows from before the hardware column: unknown hardware
    assert "Mixed numerics" in line
    assert (
        "`request threads=1` on `unknown hardware` (2 episodes), "
        "`rows=96 threads=1` on `unknown hardware` (1 episode)"
    ) in line
    # one path on two machines (a resume on other hardware, --allow-numerics-change)
    hw = pd.DataFrame(
        {
            "numerics": ["request threads=1"] * 3,
            "hardware": ["EPYC / AVX2", "Xeon / AVX512", None],
        }
    )
    (line,) = numerics_lines(hw)
    assert "`request threads=1` on `EPYC / AVX2` (1 episode)" in line
    assert "`request threads=1` on `Xeon / AVX512` (1 episode)" in line
    assert "`request threads=1` on `unknown hardware` (1 episode)" in line
    assert numerics_lines(pd.DataFrame({"numerics": [None]})) == []  # rows from before the column
    assert numerics_lines(pd.DataFrame({"x": [1]})) == []
