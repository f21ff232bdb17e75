"""``idr-eval compare``: numbers on small hand-made tables, refusals, and the MLflow selection."""

from __future__ import annotations

import json
from pathlib import Path
from urllib.parse import parse_qs

import pandas as pd
import pytest
from mlflow import MlflowClient

from pipeline import cli
from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.reporting.compare import RunEpisodes, compare, compare_table, paired_avg_diff, render
from pipeline.reporting.run_data import EPS
from pipeline.results.store import RunStore
from pipeline.tracking.ui import mlflow_lines
from tests.doubles.rows import result as hand_made

CONF = Path(__file__).resolve().parents[3] / "conf"


def _episodes(cells: dict[str, dict[str, list[int]]], errors: int = 0) -> pd.DataFrame:
    """cells: cell -> suite -> successes (0/1) by episode index; one task per suite."""
    rows = []
    for cell, suites in cells.items():
        for suite, wins in suites.items():
            for i, w in enumerate(wins):
                rows.append(
                    {
                        "cell_id": cell,
                        "mode": "baseline" if cell == "baseline" else "E",
                        "backbone": "bb",
                        "suite": suite,
                        "task_id": f"{suite}/0",
                        "episode_index": i,
                        "seed": 0,
                        "success": bool(w),
                        "error": "boom" if i < errors and cell != "baseline" else None,
                    }
                )
    return pd.DataFrame(rows)


A = {
    "baseline": {"s1": [1, 1, 0, 0], "s2": [1, 0, 0, 0]},
    "E": {"s1": [1, 1, 1, 0], "s2": [1, 1, 0, 1]},
}


def test_paper_shape_numbers_by_hand() -> None:
    table = compare_table([RunEpisodes("a", None, _episodes(A))], n_boot=500)
    rows = table.set_index("cell")
    assert list(table["cell"]) == ["baseline", "E"]  # the baseline first
    assert rows.loc["baseline", ["s1", "s2", "avg"]].tolist() == [0.5, 0.25, 0.375]
    assert rows.loc["E", ["s1", "s2", "avg"]].tolist() == [0.75, 0.75, 0.75]
    e = rows.loc["E"]
    # per-suite paired differences: s1 (0, 0, 1, 0) -> 0.25, s2 (0, 1, 0, 1) -> 0.5; Avg of them
    assert e["diff"] == pytest.approx(0.375) and e["n_pairs"] == 4 + 4
    assert e["p_value"] == pytest.approx(2 * 0.5**3)  # 3 discordant pairs, all for E
    assert 0.0 <= e["ci_low"] <= 0.375 <= e["ci_high"] <= 0.75
    assert e["baseline"] == "a/baseline"
    assert pd.isna(rows.loc["baseline", "diff"])
    md = render(table, ["s1", "s2"])
    assert "| a | E | 75.00 | 75.00 | 75.00 | +37.50 [" in md
    assert "(n=8, vs a/baseline) | 0.25 | 8 |" in md


def test_degenerate_interval_and_error_rows() -> None:
    every = {"s1": [1, 1, 1], "s2": [1, 1, 1]}
    none = {"s1": [0, 0, 0], "s2": [0, 0, 0]}
    d = paired_avg_diff(
        _episodes({"E": every}, errors=1), _episodes({"baseline": none}), n_boot=200
    )
    # the error episode (index 0 of each suite) is not a pair: 2 pairs per suite, all +1
    assert (d["diff"], d["ci_low"], d["ci_high"], d["n_pairs"]) == (1.0, 1.0, 1.0, 4)
    assert d["p_value"] == pytest.approx(2 * 0.5**4)


def test_a_run_without_baseline_pairs_with_an_earlier_run_of_the_same_keys() -> None:
    b = _episodes({"F": {"s1": [0, 0, 0, 0], "s2": [1, 0, 0, 0]}})
    table = compare_table(
        [RunEpisodes("a", None, _episodes(A)), RunEpisodes("b", None, b)], n_boot=200
    )
    f = table[(table["run"] == "b") & (table["cell"] == "F")].iloc[0]
    assert f["baseline"] == "a/baseline"
    assert f["avg"] == pytest.approx(0.125)
    assert f["diff"] == pytest.approx((0.0 - 0.5 + 0.25 - 0.25) / 2)


def test_different_task_sets_are_refused_naming_them() -> None:
    other = _episodes({"baseline": {"s1": [1, 0], "s3": [1, 1]}})
    with pytest.raises(
        ConfigError,
        match=r"the runs cover different tasks \(env.tasks\).*against a: b lacks s2/0; "
        r"b has s3/0\. Compare runs of the same suite and env.tasks",
    ):
        compare_table([RunEpisodes("a", None, _episodes(A)), RunEpisodes("b", None, other)])


def _store(run_dir: Path, df: pd.DataFrame) -> None:
    RunStore(run_dir).write(hand_made(r) for r in df.to_dict("records"))


def test_cli_compare_refuses_before_work_and_writes_on_success(tmp_path, capsys) -> None:
    _store(tmp_path / "a", _episodes(A))
    _store(tmp_path / "c", _episodes({"baseline": {"s1": [1, 0]}}))
    assert cli.main(["compare", str(tmp_path / "a"), str(tmp_path / "c")]) == 2
    err = capsys.readouterr().err
    assert "c lacks s2/0" in err and "Traceback" not in err
    assert cli.main(["compare", str(tmp_path / "a"), str(tmp_path / "nope")]) == 2
    assert "is not a run dir" in capsys.readouterr().err
    rc = cli.main(["compare", str(tmp_path / "a"), "--out", str(tmp_path / "cmp")])
    out = capsys.readouterr().out
    assert rc == 0 and "| a | E | 75.00 | 75.00 | 75.00 |" in out
    assert "No MLflow selection:" in out and "tracking.enabled=false" in out
    assert (tmp_path / "cmp" / "compare.md").read_text().startswith("# Comparison of 1 runs")


def test_mlflow_selection_shows_the_same_numbers_side_by_side(tmp_path) -> None:
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    common = [
        "executor.kind=inline",
        f"tracking.uri={uri}",
        "tracking.experiment=cmp",
        "episodes_per_task=2",
        "env.tasks=[reach]",
    ]
    for name, grid in (("r1", "[{mode: [baseline, E]}]"), ("r2", "[{mode: [baseline, F]}]")):
        cfg = load_config(CONF / "smoke.yaml", [*common, f"grid={grid}"])
        execute(plan_run(cfg, tmp_path / name))
    text, table = compare([tmp_path / "r1", tmp_path / "r2"], n_boot=200, links=mlflow_lines)
    flt = next(line.strip() for line in text.splitlines() if "attributes.run_id IN" in line)
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("cmp")
    runs = client.search_runs([exp.experiment_id], flt)
    # the Compare URL names the same runs, and the experiment, and no parent run
    url = next(w for w in text.split() if "#/compare-runs?" in w)
    assert url.startswith("http://127.0.0.1:5000/#/compare-runs?runs=")
    query = parse_qs(url.split("?", 1)[1])
    assert set(json.loads(query["runs"][0])) == {r.info.run_id for r in runs}
    assert json.loads(query["experiments"][0]) == [exp.experiment_id]
    got = {(Path(r.data.tags["idr.run_dir"]).name, r.data.tags["idr.cell"]): r for r in runs}
    assert set(got) == {("r1", "baseline"), ("r1", "E"), ("r2", "baseline"), ("r2", "F")}
    # the same param and tag keys on every cell of one mode, so the UI's comparison lines
    # them up; a baseline carries none of the IDR parameters it ignores
    refining = [r for r in runs if r.data.tags["idr.cell_role"] == "idr"]
    assert len(refining) == 2 and len({frozenset(r.data.params) for r in refining}) == 1
    for r in runs:
        assert r.data.tags["idr.role"] == "cell" and r.data.tags["idr.suite"] == "fake_marker"
        assert {"cell.mode", "suite", "backbone"} <= set(r.data.params)
        has_alpha = "cell.alpha" in r.data.params
        assert has_alpha == (r.data.tags["idr.cell_role"] == "idr")
    for row in table.to_dict("records"):  # one unit: percent (points for Δ), 4 figures
        m = got[(row["run"], row["cell"])].data.metrics
        assert m["success/fake_marker"] == pytest.approx(100 * row["fake_marker"], rel=1e-3)
        assert m["success_avg"] == pytest.approx(100 * row["avg"], rel=1e-3)
        if not pd.isna(row.get("diff")):
            assert m["delta_vs_baseline"] == pytest.approx(100 * row["diff"], rel=1e-3, abs=1e-9)


def test_compare_of_different_tasks_still_prints_the_ui_selection(tmp_path, capsys) -> None:
    """The table is refused (different tasks), and the UI still gets the runs side by side."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    common = ["executor.kind=inline", f"tracking.uri={uri}", "episodes_per_task=1"]
    for name, tasks in (("r1", "[reach]"), ("r2", "[reach_chain]")):
        cfg = load_config(CONF / "smoke.yaml", [*common, f"env.tasks={tasks}"])
        execute(plan_run(cfg, tmp_path / name))
    rc = cli.main(["compare", str(tmp_path / "r1"), str(tmp_path / "r2")])
    captured = capsys.readouterr()
    assert rc == 2 and "cover different tasks" in captured.err
    url = next(w for w in captured.out.split() if "#/compare-runs?" in w)
    ids = json.loads(parse_qs(url.split("?", 1)[1])["runs"][0])
    assert len(ids) == 4  # 2 cells x 2 runs
    client = MlflowClient(uri)
    cells = {client.get_run(i).data.tags["idr.cell"] for i in ids}
    assert cells == {"baseline", "E"}


def test_across_suites_sets_runs_of_different_tasks_side_by_side(tmp_path, capsys) -> None:
    """--across-suites: runs the paired table refuses (other tasks) get one unpaired row per run
    x suite, with the reference cell's success and the diagnose cell's R_img (its ratio of
    time averages, recomputed here from the stored steps)."""
    common = [
        "executor.kind=inline",
        "tracking.enabled=false",
        "episodes_per_task=2",
        "grid=[{mode: [baseline, diagnose]}]",
    ]
    for name, tasks in (("r1", "[reach]"), ("r2", "[reach_chain]")):
        cfg = load_config(CONF / "smoke.yaml", [*common, f"env.tasks={tasks}"])
        execute(plan_run(cfg, tmp_path / name))
    runs = [str(tmp_path / "r1"), str(tmp_path / "r2")]
    assert cli.main(["compare", *runs]) == 2  # the paired table: refused
    capsys.readouterr()
    out = tmp_path / "cmp"
    assert cli.main(["compare", *runs, "--across-suites", "--out", str(out)]) == 0
    _, table = compare(runs, across_suites=True)
    assert list(table["run"]) == ["r1", "r2"] and set(table["cell"]) == {"baseline"}
    for row in table.to_dict("records"):
        store = RunStore(tmp_path / row["run"])
        eps = store.episodes().to_pandas()
        assert row["success"] == eps[eps.cell_id == "baseline"].success.mean()
        steps = store.steps().to_pandas()
        diag = steps[(steps.cell_id == "diagnose")].dropna(subset=["e_img", "e_prop"])
        want = diag.e_img.mean() / (diag.e_img.mean() + diag.e_prop.mean() + EPS)
        assert row["r_img"] == pytest.approx(want, rel=1e-6) and 0 < row["r_img"] < 1
    assert (out / "compare.md").read_text().startswith("# R_img and success across 2 runs")
    assert (out / "figures" / "rimg_heatmap.png").is_file()
