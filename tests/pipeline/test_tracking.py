"""MLflow: one parent run and one child per cell, with the cell's params and the metrics."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from mlflow import MlflowClient

from pipeline.config import ConfigError, load_config
from pipeline.runner import execute, plan_run
from pipeline.store import RunStore

CONF = Path(__file__).resolve().parents[2] / "conf"


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
        assert run.data.metrics["success"] == pytest.approx(sub.success.mean())
        assert run.data.metrics["success/fake_marker"] == pytest.approx(sub.success.mean())
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
        assert rate == pytest.approx(sub.success.mean())
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
