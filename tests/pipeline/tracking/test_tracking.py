"""MLflow: one parent run and one child per cell, with the cell's params and the metrics."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from mlflow import MlflowClient

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.results.store import RunStore

CONF = Path(__file__).resolve().parents[3] / "conf"


def test_parent_and_one_child_per_cell(tmp_path) -> None:
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.kind=inline",
            f"tracking.uri={uri}",
            "tracking.experiment=t",
            "grid=[{mode: [baseline, E, F]}]",
        ],
    )
    execute(plan_run(cfg, tmp_path / "run"))
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("t")
    runs = client.search_runs([exp.experiment_id])
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert len(parents) == 1 and len(children) == 3
    (parent,) = parents
    assert {c.data.tags["mlflow.parentRunId"] for c in children} == {parent.info.run_id}
    assert parent.info.status == "FINISHED" and parent.data.params["suite"] == "fake_marker"
    by_cell = {c.data.tags["idr.cell"]: c for c in children}
    assert set(by_cell) == {"baseline", "E", "F"}
    f = by_cell["F"].data
    assert (
        f.params["cell.mode"] == "F"
        and f.params["cell.alpha"] == "0.08"
        and f.tags["idr.tau"] == "7.0"
    )
    # metrics equal what the episodes table says
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    for cell, run in by_cell.items():
        sub = eps[eps.cell_id == cell]
        pct = 100 * sub.success.mean()  # percent, as in the report and compare
        assert run.data.metrics["success"] == pytest.approx(pct, rel=1e-3)
        assert run.data.metrics["success/fake_marker"] == pytest.approx(pct, rel=1e-3)
        chain = sub[sub.task_id == "reach_chain"].subtasks_done.mean()
        assert run.data.metrics["avg_len"] == pytest.approx(chain)
        assert run.data.metrics["avg_len/fake_marker"] == pytest.approx(chain)
        # no metric name per task: their count must not grow with the benchmark
        assert not [m for m in run.data.metrics if "reach" in m], run.data.metrics
        # failed episodes by cause (the fake ends episodes only at max_steps: all timeouts)
        assert run.data.metrics.get("failures/timeout", 0.0) == (~sub.success).sum()
    assert (
        "gate_rate" in by_cell["E"].data.metrics
        and "gate_rate" not in by_cell["baseline"].data.metrics
    )
    assert "delta_vs_baseline" in by_cell["E"].data.metrics
    arts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"report.md", "config.yaml", "tables"} <= arts
    # per-task numbers: one table for the whole grid, as the parent's artifact
    table = Path(client.download_artifacts(parent.info.run_id, "tables/success_by_task.csv"))
    per_task = pd.read_csv(table).set_index(["cell_id", "task_id"])["success_rate"]
    for (cell, task), rate in per_task.items():
        sub = eps[(eps.cell_id == cell) & (eps.task_id == task)]
        assert rate == pytest.approx(100 * sub.success.mean())
    assert len(per_task) == 3 * 2
    # resume logs into the same runs
    execute(plan_run(cfg, tmp_path / "run"))
    assert len(client.search_runs([exp.experiment_id])) == 4


def test_unreachable_server_is_refused_before_work(tmp_path) -> None:
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = load_config(
        CONF / "smoke.yaml", ["executor.kind=inline", f"tracking.uri=http://127.0.0.1:{port}"]
    )
    with pytest.raises(ConfigError, match=r"tracking.uri: MLflow store .* is not usable"):
        execute(plan_run(cfg, tmp_path / "run"))
    assert not list((tmp_path / "run").rglob("*.parquet"))


def test_the_ui_shows_what_each_cell_means(tmp_path) -> None:
    """Params only where the mode uses them, the role as a tag, the numeric tau used, rounded
    metrics, per-cell artifacts (report slice as HTML with its figures embedded), progress
    curves as step-indexed metrics, and nothing per cell in the parent's metric names."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.kind=inline",
            f"tracking.uri={uri}",
            "tracking.experiment=ui",
            "episodes_per_task=2",
            "idr.tau=calibrated",
            "grid=[{mode: [baseline, diagnose, E, D]}]",
        ],
    )
    execute(plan_run(cfg, tmp_path / "run"))
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("ui")
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"  # not the GenAI view
    runs = client.search_runs([exp.experiment_id])
    parent = next(r for r in runs if "mlflow.parentRunId" not in r.data.tags)
    cells = {r.data.tags["idr.cell"]: r for r in runs if "mlflow.parentRunId" in r.data.tags}
    params = {c: {k for k in r.data.params if k.startswith("cell.")} for c, r in cells.items()}
    assert params["baseline"] == {"cell.mode"}
    assert "cell.alpha" not in params["diagnose"] and "cell.tau" not in params["diagnose"]
    assert {"cell.strategy", "cell.eps"} <= params["diagnose"]
    assert {"cell.alpha", "cell.tau", "cell.tau_value"} <= params["E"]
    assert "cell.tau" not in params["D"] and "cell.tau_value" not in params["D"]  # no gate
    roles = {c: r.data.tags["idr.cell_role"] for c, r in cells.items()}
    assert roles == {"baseline": "baseline", "diagnose": "diagnose", "E": "idr", "D": "idr"}
    # the tau E used: the diagnose cell's mean E_img, a plottable number
    steps = RunStore(tmp_path / "run").steps(columns=["cell_id", "e_img"]).to_pandas()
    mean_e = steps[steps.cell_id == "diagnose"].e_img.mean()
    assert float(cells["E"].data.params["cell.tau_value"]) == pytest.approx(mean_e, rel=1e-3)
    assert cells["E"].data.params["cell.tau"] == "calibrated"
    # 4 significant figures at most
    for r in cells.values():
        for v in r.data.metrics.values():
            assert v == float(f"{v:.4g}") or v.is_integer(), v
    # the parent: run-level metrics only, per-cell numbers in one table
    assert not [m for m in parent.data.metrics if any(c in m for c in cells)], parent.data.metrics
    table = pd.read_csv(client.download_artifacts(parent.info.run_id, "tables/cells.csv"))
    assert set(table["cell"]) == set(cells)
    e_row = table.set_index("cell").loc["E"]
    assert e_row["success"] == cells["E"].data.metrics["success"]
    # each child is self-contained: its report slice (HTML, figures embedded), figures, table
    e_id = cells["E"].info.run_id
    arts = {a.path for a in client.list_artifacts(e_id)}
    assert {"report.md", "report.html", "figures", "tables"} <= arts
    figs = {a.path for a in client.list_artifacts(e_id, "figures")}
    assert figs == {"figures/rimg_progress.png", "figures/gate_progress.png"}
    page = Path(client.download_artifacts(e_id, "report.html")).read_text()
    assert page.count('src="data:image/png;base64,') == 2 and "figures/" not in page
    assert "# Cell `E`" in Path(client.download_artifacts(e_id, "report.md")).read_text()
    parent_page = Path(client.download_artifacts(parent.info.run_id, "report.html")).read_text()
    assert 'src="data:image/png;base64,' in parent_page
    # progress curves: one point per progress bin, step = % of the episode
    hist = client.get_metric_history(e_id, "progress/r_img")
    got = sorted(m.step for m in hist)  # a bin without an inference has no point
    assert set(got) <= set(range(5, 100, 10)) and len(got) >= 8 and len(set(got)) == len(got)
    assert all(0.0 <= m.value <= 1.0 for m in hist)
    gate = client.get_metric_history(e_id, "progress/gate_rate")
    assert sorted(m.step for m in gate) == got
    assert not client.get_metric_history(cells["diagnose"].info.run_id, "progress/gate_rate")
    assert not client.get_metric_history(cells["baseline"].info.run_id, "progress/r_img")
