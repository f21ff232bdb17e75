"""Fault 3, the driver stopped by SIGTERM or SIGINT: finished episodes are flushed, files
closed, MLflow runs marked KILLED, exit 128+signal; the next ``idr-eval run`` on the same
RUN_DIR resumes and completes. (SIGKILL: tests/pipeline/execution/test_scheduler.py.)"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.execution.signals import RunInterrupted, stop_on_signals
from pipeline.planning.config import load_config
from tests.support.fault_audit import assert_clean, audit

ROOT = Path(__file__).resolve().parents[2]
EXPECTED = {(c, "reach", i) for c in ("baseline", "E") for i in range(3)}
GUARANTEE = (
    "finished episodes flushed, files closed, MLflow runs KILLED, exit 128+signal; the same "
    "command resumes"
)


def _overrides(once: Path) -> list[str]:
    return [
        "env.tasks=[reach]",
        "executor.flush_every=100",  # nothing is written before the stop: the stop flushes
        # episode 2 (the third, in order) hangs the first time: the signal lands there
        "env.suite=tests.doubles.envs:FaultyMarkerEnv",
        f"env.params={{hang_on: [2], once_dir: {once}}}",
    ]


def _wait_for(marker: Path, proc: subprocess.Popen | None = None) -> None:
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not marker.exists():
        assert proc is None or proc.poll() is None, proc.communicate()[1]
        time.sleep(0.05)
    assert marker.exists(), "the run never reached the hanging episode"


def _statuses(run_dir: Path) -> set[str]:
    from mlflow import MlflowClient

    state = json.loads((run_dir / "tracking.json").read_text())
    client = MlflowClient(tracking_uri=state["uri"])
    return {client.get_run(i).info.status for i in [state["parent"], *state["children"].values()]}


def _check_stopped(out: Path) -> dict:
    stopped = audit(out, EXPECTED)
    assert_clean(stopped, complete=False)
    assert stopped["stored"] == 2  # the two episodes finished before the stop, flushed by it
    assert (out / "report.md").is_file()
    assert _statuses(out) == {"KILLED"}
    return stopped


def _resume(out: Path, once: Path) -> dict:
    """What ``idr-eval run`` on the same RUN_DIR does, in this process (an extra CLI process
    costs ~20 s of imports here); inline: the executor is not part of a run's identity."""
    cfg = load_config(ROOT / "conf/smoke.yaml", [*_overrides(once), "executor.kind=inline"])
    summary = execute(plan_run(cfg, out))
    assert summary.skipped == 2 and summary.stored == 4
    resumed = audit(out, EXPECTED)
    assert_clean(resumed)
    assert resumed["error_rows"] == 0
    assert _statuses(out) == {"FINISHED"}
    return resumed


@pytest.mark.slow
def test_sigterm_to_the_cli_on_ray(tmp_path, ray_local, fault_log) -> None:
    """The real CLI process, a driver of the session's Ray cluster: ray.init installs its own
    SIGTERM handler (which aborts), so this also checks that ours is put back."""
    out, once = tmp_path / "run", tmp_path / "once"
    address = ray_local.get_runtime_context().gcs_address
    args = ["run", "conf/smoke.yaml", "--out", str(out), *_overrides(once)]
    args += ["executor.kind=ray", "executor.workers=1", f"executor.address={address}"]
    proc = subprocess.Popen(
        [sys.executable, "-m", "pipeline.cli", *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    _wait_for(once / "hang-2", proc)
    os.kill(proc.pid, signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, stderr
    assert "stopped by SIGTERM" in stderr and "run the same command again to resume" in stderr
    assert "Traceback" not in stderr
    stopped = _check_stopped(out)
    resumed = _resume(out, once)
    fault_log.record(
        "driver stopped by SIGTERM (ray)",
        "SIGTERM to the `idr-eval run` process while an episode hangs; then resume",
        GUARANTEE,
        {**resumed, "stored_at_stop": stopped["stored"], "exit_code": proc.returncode},
    )


def test_sigint_inline(tmp_path, fault_log) -> None:
    """Ctrl-C, in this process: the same handlers the CLI installs."""
    out, once = tmp_path / "run", tmp_path / "once"
    cfg = load_config(ROOT / "conf/smoke.yaml", [*_overrides(once), "executor.kind=inline"])
    plan = plan_run(cfg, out)
    threading.Thread(
        target=lambda: (_wait_for(once / "hang-2"), os.kill(os.getpid(), signal.SIGINT)),
        daemon=True,
    ).start()
    with pytest.raises(RunInterrupted) as stop, stop_on_signals():
        execute(plan)
    assert stop.value.signum == signal.SIGINT and stop.value.exit_code == 130
    stopped = _check_stopped(out)
    resumed = _resume(out, once)
    fault_log.record(
        "driver stopped by SIGINT (inline)",
        "SIGINT (Ctrl-C) to the driver while an episode hangs; then resume",
        GUARANTEE,
        {**resumed, "stored_at_stop": stopped["stored"], "exit_code": stop.value.exit_code},
    )


def test_a_signal_waits_for_the_batch_being_written() -> None:
    """Inside a critical section (a Parquet batch and its bookkeeping) the stop is held back
    and raised when the section ends; an error inside the section wins over it."""
    from pipeline.execution.signals import critical_section

    done, before = [], signal.getsignal(signal.SIGTERM)
    with pytest.raises(RunInterrupted) as stop, stop_on_signals():
        with critical_section():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)  # the handler has run by now: held back
            done.append("batch written")
        done.append("never")
    assert done == ["batch written"] and stop.value.exit_code == 143

    with pytest.raises(OSError, match="disk"), stop_on_signals(), critical_section():
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.05)
        raise OSError("disk")
    assert signal.getsignal(signal.SIGTERM) is before  # handlers restored
