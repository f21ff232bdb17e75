"""The MLflow store misbehaving: drivers started at once on a new output root (one new SQLite
store), a damaged store, a path or scheme that cannot work. Real drivers (subprocesses of the
CLI), a real SQLite store; nothing lost, and every refusal before anything is created."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.execution.runner import plan_run
from pipeline.planning.config import ConfigError, load_config
from tests.support.fault_audit import assert_clean, audit

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"


def _cmd(out: Path, *extra: str) -> list[str]:
    return [
        sys.executable, "-m", "pipeline.cli", "run", "conf/smoke.yaml", "--out", str(out),
        "executor.kind=inline", *extra,
    ]  # fmt: skip


@pytest.mark.slow
def test_four_drivers_started_at_once_on_a_new_store_all_finish(tmp_path, fault_log) -> None:
    root = tmp_path / "runs"  # new: no mlflow.db yet, all four create it at once
    runs = [root / f"run{i}" for i in range(4)]
    t0 = time.monotonic()
    procs = [
        subprocess.Popen(
            _cmd(r), cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        for r in runs
    ]
    outs = [p.communicate(timeout=600) for p in procs]
    seconds = time.monotonic() - t0
    for p, (_, err) in zip(procs, outs, strict=True):
        assert p.returncode == 0, err[-3000:]
        assert "Traceback" not in err, err[-3000:]
    from mlflow import MlflowClient

    client = MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    exp = client.get_experiment_by_name("idr-eval")
    parents = [
        r
        for r in client.search_runs([exp.experiment_id])
        if "mlflow.parentRunId" not in r.data.tags
    ]
    assert len(parents) == 4 and {r.info.status for r in parents} == {"FINISHED"}
    outcomes = []
    for run_dir in runs:
        plan = plan_run(load_config(CONF / "smoke.yaml", ["executor.kind=inline"]), run_dir)
        outcome = audit(run_dir, {s.key for s in plan.all_specs()})
        assert_clean(outcome)
        outcomes.append(outcome)
    for parent in parents:
        assert parent.data.metrics["episodes_stored"] == outcomes[0]["expected"]
    fault_log.record(
        "four drivers started at once on a new output root (one new SQLite MLflow store)",
        "4 `idr-eval run` subprocesses launched together, no mlflow.db beforehand",
        "the store is created and migrated under a lock of its own; every run and metric recorded",
        {"drivers": 4, "finished": 4, "seconds": round(seconds, 1), **outcomes[0]},
    )


def _refused(tmp_path: Path, uri: str, match: str) -> None:
    run_dir = tmp_path / "runs" / "run"
    cfg = load_config(CONF / "smoke.yaml", ["executor.kind=inline", f"tracking.uri={uri}"])
    with pytest.raises(ConfigError, match=match):
        plan_run(cfg, run_dir)
    assert not run_dir.exists()  # refused before anything was created


def test_a_damaged_store_is_refused_before_anything_is_created(tmp_path, fault_log) -> None:
    store = tmp_path / "mlflow.db"
    uri = f"sqlite:///{store}"
    cfg = load_config(CONF / "smoke.yaml", ["executor.kind=inline", f"tracking.uri={uri}"])
    from pipeline.tracking.tracker import Tracker

    Tracker(uri, "idr-eval", tmp_path)  # a real store, then truncated as a full disk leaves it
    data = store.read_bytes()
    store.write_bytes(data[: len(data) // 3])
    t0 = time.monotonic()
    with pytest.raises(ConfigError) as e:
        plan_run(cfg, tmp_path / "runs" / "run")
    msg = str(e.value)
    assert f"{store} is not a readable MLflow store" in msg
    assert "move it aside" in msg and "tracking.enabled=false" in msg
    assert not (tmp_path / "runs" / "run").exists()
    store.write_bytes(b"this is not a database" * 100)
    with pytest.raises(ConfigError, match="is not a readable MLflow store"):
        plan_run(cfg, tmp_path / "runs" / "run")
    fault_log.record(
        "a damaged SQLite MLflow store (truncated to a third, or not a database)",
        "mlflow.db truncated after a real store was made; then overwritten with text",
        "refused before anything is created, one message naming the file and the fix",
        {"seconds_to_refusal": round(time.monotonic() - t0, 2), "run_dir_created": False},
    )


def test_store_paths_and_schemes_that_cannot_work_are_refused(tmp_path) -> None:
    (tmp_path / "a_dir.db").mkdir()
    _refused(tmp_path, f"sqlite:///{tmp_path / 'a_dir.db'}", r"is a directory: give a file path")
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    try:
        import os

        if os.geteuid() != 0:  # root writes anywhere: the permission check cannot fail
            _refused(tmp_path, f"sqlite:///{locked / 'mlflow.db'}", r"cannot be written")
    finally:
        locked.chmod(0o700)
    _refused(tmp_path, "ftp://example.org/store", r"unknown scheme 'ftp': use sqlite:///PATH")
    _refused(tmp_path, "mlflow.db", r"unknown scheme '\(none\)'")


def test_a_store_that_fails_mid_run_holds_updates_back(tmp_path) -> None:
    """A SQLite store that stops answering during a run (here: moved away) is an outage like a
    server's: updates are held back, nothing raises, and they are sent once it is back."""
    from pipeline.tracking.tracker import Tracker

    store = tmp_path / "mlflow.db"
    tracker = Tracker(f"sqlite:///{store}", "idr-eval", tmp_path, reconnect_wait_s=0)
    tracker.start(run_name="r", run_id="r1", params={}, cells=[])
    store.rename(tmp_path / "away.db")
    tracker.progress(3, 10)  # no exception: held back
    assert not tracker.online and len(tracker._pending) == 1
    (tmp_path / "away.db").rename(store)
    tracker._next_probe = 0.0
    assert tracker._flush_pending() and not tracker._pending
    history = tracker.client.get_metric_history(tracker.parent_id, "episodes_stored")
    assert [m.value for m in history] == [3]
