"""MLflow on a tracking server backed by PostgreSQL, as on a cluster.

A throwaway PostgreSQL (initdb as an unprivileged user when run as root) and ``mlflow server
--backend-store-uri postgresql://...`` on free ports of 127.0.0.1. A run logs there exactly
what it logs to the default SQLite store; the server is killed mid-run: the run keeps writing
Parquet and MLflow is completed once the server answers again. The state machine for a server
that stays down (the run says so, a rerun completes MLflow) is tested without a server.
"""

from __future__ import annotations

import logging
import sys
import threading
import time
from pathlib import Path

import pytest
from mlflow import MlflowClient

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config
from pipeline.results.store import RunStore
from pipeline.rundir import TRACKING_FILE
from pipeline.tracking import tracker as tracking
from pipeline.tracking.backend import default_uri

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from localcluster import MlflowServer, Postgres, postgres_bin

CONF = Path(__file__).resolve().parents[3] / "conf"
SMOKE = [
    "executor.kind=inline",
    "executor.flush_every=1",
    "backbone.params.busy_s=0.05",  # episodes of ~0.3 s: time to lose the server mid-run
    "tracking.experiment=t",
]


def _batches(run_dir: Path) -> int:
    return len(list((run_dir / "episodes").glob("cell=*/batch-*.parquet")))


def _runs(uri: str) -> tuple[object, dict[str, object]]:
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("t")
    runs = client.search_runs([exp.experiment_id])
    (parent,) = [r for r in runs if r.data.tags.get("idr.role") == "run"]
    children = {r.data.tags["idr.cell"]: r for r in runs if r.data.tags.get("idr.role") == "cell"}
    return parent, children


def _shape(uri: str) -> dict[str, object]:
    """What a run logged, minus what differs between two runs (ids, paths, times)."""
    parent, children = _runs(uri)
    client = MlflowClient(uri)

    def one(r) -> dict[str, object]:
        return {
            "status": r.info.status,
            "params": {k: v for k, v in r.data.params.items() if k != "fingerprint"},
            "metrics": {
                k: round(v, 9)
                for k, v in r.data.metrics.items()
                if k not in ("wall_seconds_per_episode", "inference_ms")
            },
            "tags": sorted(k for k in r.data.tags if not k.startswith("mlflow.")),
        }

    stored = client.get_metric_history(parent.info.run_id, "episodes_stored")
    return {
        "parent": one(parent),
        "children": {c: one(r) for c, r in children.items()},
        "episodes_stored": max(m.value for m in stored),
        "artifacts": sorted(a.path for a in client.list_artifacts(parent.info.run_id)),
    }


@pytest.mark.slow
@pytest.mark.timeout(300)
@pytest.mark.skipif(postgres_bin() is None, reason="PostgreSQL is not installed")
def test_postgres_server_like_sqlite_and_survives_going_down(tmp_path, caplog) -> None:
    pytest.importorskip("psycopg", reason="the server extra (psycopg) is not installed")
    caplog.set_level(logging.INFO, logger="idr_eval")
    with Postgres() as pg, MlflowServer(pg.url, tmp_path / "artifacts") as server:
        run_dir = tmp_path / "server-run"
        cfg = load_config(
            CONF / "smoke.yaml",
            [*SMOKE, f"tracking.uri={server.uri}", "tracking.reconnect_wait_s=120"],
        )
        plan = plan_run(cfg, run_dir)
        timeline: dict[str, float] = {}

        def outage() -> None:  # kill the server after 2 batches, restart it after 2 more
            while _batches(run_dir) < 2:
                time.sleep(0.02)
            server.stop()
            timeline["down_at_batch"] = _batches(run_dir)
            while _batches(run_dir) < timeline["down_at_batch"] + 2:
                time.sleep(0.02)
            timeline["restart_at_batch"] = _batches(run_dir)
            server.start()
            timeline["up_at_batch"] = _batches(run_dir)

        killer = threading.Thread(target=outage, daemon=True)
        killer.start()
        summary = execute(plan)
        killer.join(timeout=200)
        assert summary.stored == 12 and summary.errors == 0
        assert len(RunStore(run_dir).stored_keys()) == 12  # Parquet went on while it was down
        assert timeline["restart_at_batch"] >= timeline["down_at_batch"] + 2
        messages = caplog.text
        assert "is down" in messages and "answers again" in messages
        remote = _shape(server.uri)

    # the same run on the default SQLite store logs the same things
    sqlite_run = tmp_path / "local" / "run"
    execute(plan_run(load_config(CONF / "smoke.yaml", SMOKE), sqlite_run))
    local = _shape(default_uri(sqlite_run))
    assert remote == local
    assert remote["parent"]["status"] == "FINISHED" and remote["episodes_stored"] == 12
    assert {"report.md", "config.yaml"} <= set(remote["artifacts"])


class _Flaky:
    """An MlflowClient whose server is down while ``down`` is set."""

    def __init__(self, real: MlflowClient) -> None:
        self.real, self.down, self.calls = real, False, 0

    def __getattr__(self, name: str):
        attr = getattr(self.real, name)

        def call(*args, **kwargs):
            self.calls += 1
            if self.down:
                raise ConnectionError("Connection refused")
            return attr(*args, **kwargs)

        return call


def test_a_server_down_at_the_end_is_reported_and_a_rerun_completes_mlflow(
    tmp_path, monkeypatch, caplog
) -> None:
    """No server needed: the tracker's outage handling, with the store's calls made to fail."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    tracker = tracking.Tracker(uri, "t", tmp_path, reconnect_wait_s=0.3)
    tracker._server = True  # handle outages as for an http:// store
    flaky = tracker.client = _Flaky(tracker.client)
    alive = {"up": True}
    monkeypatch.setattr(tracking, "answers", lambda _uri: alive["up"])
    monkeypatch.setattr(tracking, "RECHECK_S", 0.05)
    cfg = load_config(CONF / "smoke.yaml", ["executor.kind=inline"])
    tracker.start(run_name="r", run_id="abc", params={"suite": "fake_marker"}, cells=cfg.cells())
    tracker.progress(4, 12)
    flaky.down, alive["up"] = True, False  # the server goes down
    tracker.progress(4, 12)  # held back, the run goes on
    tracker.progress(4, 12)
    n = flaky.calls
    tracker.progress(4, 12)
    assert flaky.calls == n  # while down, no call is even tried (no minutes of retries)
    import pandas as pd

    t0 = time.monotonic()
    assert tracker.finish(pd.DataFrame(), [], "FINISHED") is False
    assert time.monotonic() - t0 < 5
    assert "MLflow was not updated" in caplog.text and "run the same" in caplog.text
    assert MlflowClient(uri).get_run(tracker.parent_id).info.status == "RUNNING"
    flaky.down, alive["up"] = False, True  # back: the held-back updates go out first
    assert tracker.finish(pd.DataFrame(), [], "FINISHED") is True
    client = MlflowClient(uri)
    assert client.get_run(tracker.parent_id).info.status == "FINISHED"
    history = [m.value for m in client.get_metric_history(tracker.parent_id, "episodes_stored")]
    assert max(history) == 16


def test_ui_of_a_remote_server_says_how_to_open_it(tmp_path, capsys) -> None:
    import json

    from pipeline import cli

    (tmp_path / TRACKING_FILE).write_text(
        json.dumps({"uri": "http://mlflow.idr-eval.svc.cluster.local:5000", "parent": "p"})
    )
    assert cli.main(["ui", str(tmp_path)]) == 0  # starts nothing: the server has its own UI
    out = capsys.readouterr().out
    assert "ssh -N -L 5000:mlflow.idr-eval.svc.cluster.local:5000" in out
    assert "kubectl port-forward svc/mlflow 5000:5000" in out
    assert "http://127.0.0.1:5000" in out
