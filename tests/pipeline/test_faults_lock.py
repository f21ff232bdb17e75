"""Two drivers on one run dir: the second is refused with who holds it; a dead driver's lock
is taken over. Real drivers (subprocesses of the CLI), real flock."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

import pytest

from pipeline.execution.lock import RunDirLock
from pipeline.planning.config import ConfigError
from pipeline.results.store import RunStore
from pipeline.rundir import LOCK_FILE
from tests.support.fault_audit import assert_clean, audit

ROOT = Path(__file__).resolve().parents[2]


def _cmd(out: Path, *extra: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "pipeline.cli",
        "run",
        "conf/smoke.yaml",
        "--out",
        str(out),
        "executor.kind=inline",
        "tracking.enabled=false",
        "executor.flush_every=1",
        *extra,
    ]


def _keys(run_dir: Path) -> Counter:
    t = RunStore(run_dir, read_only=True).episodes().to_pydict()
    return Counter(zip(t["cell_id"], t["task_id"], t["episode_index"], strict=True))


def test_the_lock_names_its_holder_and_is_released(tmp_path) -> None:
    with RunDirLock(tmp_path / "run") as held:
        record = held.holder()
        assert record["pid"] == os.getpid() and record["host"]
        with pytest.raises(
            ConfigError, match=rf"in use by another idr-eval driver \(pid {os.getpid()}"
        ):
            RunDirLock(tmp_path / "run").acquire()
    with RunDirLock(tmp_path / "run"):  # released: free again
        pass


def test_a_second_driver_is_refused_and_the_first_completes(tmp_path, fault_log) -> None:
    out = tmp_path / "run"
    gate = tmp_path / "gate"  # the first driver's episodes wait for it: it holds the run dir
    args = _cmd(
        out,
        "backbone.kind=tests.doubles.backbones:GatedMarkerBackbone",
        f"backbone.params.gate={gate}",
    )
    first = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and not (out / "run.json").is_file():
        time.sleep(0.05)
    second = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=120)
    gate.touch()
    first_err = first.communicate(timeout=300)[1].decode()
    assert first.returncode == 0, first_err
    assert second.returncode == 2 and "Traceback" not in second.stderr
    assert f"in use by another idr-eval driver (pid {first.pid} on host" in second.stderr
    keys = _keys(out)
    assert len(keys) == 12 and set(keys.values()) == {1}
    cells, tasks = ("baseline", "E"), ("reach", "reach_chain")
    outcome = audit(out, {(c, t, i) for c in cells for t in tasks for i in range(3)})
    assert_clean(outcome)
    fault_log.record(
        "two drivers on one RUN_DIR",
        "the same `idr-eval run` started again while the first runs",
        "the second is refused (exit 2) naming the holder's pid and host, before it starts "
        "anything; the first completes, every key stored once",
        {**outcome, "second_exit_code": second.returncode},
    )


def test_a_dead_drivers_lock_is_taken_over(tmp_path, fault_log) -> None:
    """The record of a driver that died (its flock gone with it) does not block a resume."""
    out = tmp_path / "run"
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    out.mkdir()
    (out / LOCK_FILE).write_text(json.dumps({"host": os.uname().nodename, "pid": dead.pid}))
    from pipeline.execution.runner import execute, plan_run
    from pipeline.planning.config import load_config

    cfg = load_config(
        ROOT / "conf" / "smoke.yaml", ["executor.kind=inline", "tracking.enabled=false"]
    )
    execute(plan_run(cfg, out))  # this process takes the lock over
    keys = _keys(out)
    assert len(keys) == 12 and set(keys.values()) == {1}
    assert (out / LOCK_FILE).read_text() == ""  # released at the end
    fault_log.record(
        "stale lock of a dead driver",
        "RUN_DIR/.lock naming a driver process that has exited",
        "taken over (the kernel dropped its flock); the run completes",
        {"stored": len(keys), "stored_twice": 0},
    )
