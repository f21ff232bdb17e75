"""Fault 4, the disk fills up while Parquet is written (a real tmpfs of a few MB, filled to
the last byte mid-run): one clear error, no partial or unreadable file, the keys stored
before intact; once space is freed the same command resumes and completes the run."""

from __future__ import annotations

import errno
import os
import subprocess
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.errors import DiskFullError
from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config
from pipeline.results.store import RunStore
from tests.support.fault_audit import assert_clean, audit

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def small_disk(tmp_path):
    """A 4 MB tmpfs (the tests run as root in CI; skipped where mounting is not permitted)."""
    mnt = tmp_path / "disk"
    mnt.mkdir()
    r = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mnt)], capture_output=True, text=True
    )
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here (needs root or CAP_SYS_ADMIN): {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], check=False)


def fill(disk: Path) -> Path:
    """Write a file until the device is full; return it (delete it to free the space)."""
    filler = disk / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    try:
        while True:
            os.write(fd, b"\0" * 65536)  # partial writes near the end, then ENOSPC
    except OSError as e:
        assert e.errno == errno.ENOSPC
    finally:
        os.close(fd)
    return filler


def test_disk_full_mid_run_then_resume(small_disk, monkeypatch, capsys, fault_log) -> None:
    out = small_disk / "run"
    overrides = ["tracking.enabled=false", "executor.kind=inline", "executor.flush_every=1"]
    cfg = load_config(ROOT / "conf/smoke.yaml", overrides)
    plan = plan_run(cfg, out)
    expected = {s.key for s in plan.all_specs()}

    written, real_write = [], RunStore.write

    def write_then_fill(self, results):
        n = real_write(self, results)
        written.append(n)
        if len(written) == 3:
            fill(small_disk)  # the 4th batch meets a full disk
        return n

    monkeypatch.setattr(RunStore, "write", write_then_fill)
    with pytest.raises(DiskFullError) as err:
        execute(plan)
    msg = str(err.value)
    assert "no space left on the device" in msg and "3 episodes stored before are intact" in msg
    assert "run the same command again to resume" in msg
    stopped = audit(out, expected)
    assert_clean(stopped, complete=False)
    assert stopped["stored"] == 3 and stopped["error_rows"] == 0

    # the CLI on the still-full disk: one line, exit 1, no traceback, nothing written
    monkeypatch.setattr(RunStore, "write", real_write)
    argv = ["run", str(ROOT / "conf/smoke.yaml"), "--out", str(out), *overrides]
    assert cli.main(argv) == 1
    stderr = capsys.readouterr().err
    assert stderr.count("idr-eval: error:") == 1 and "no space left on the device" in stderr
    assert "Traceback" not in stderr
    assert audit(out, expected) == stopped
    assert load_config(out / "config.yaml")  # rewritten whole or not at all, never truncated

    (small_disk / "filler").unlink()  # space freed: the same command resumes
    assert cli.main(argv) == 0
    assert "9 stored, 3 already stored" in capsys.readouterr().out
    resumed = audit(out, expected)
    assert_clean(resumed)
    fault_log.record(
        "disk full while writing Parquet",
        "4 MB tmpfs filled to the last byte after the 3rd batch; the CLI rerun on the full disk; "
        "space freed; the same command again",
        "one clear error (exit 1), no partial or unreadable file, the stored keys intact; resume "
        "completes the run",
        {**resumed, "stored_at_error": stopped["stored"]},
    )
