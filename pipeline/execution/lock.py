"""One driver per run directory: an advisory lock on ``RUN_DIR/.lock`` held for the whole run.

Two drivers on one RUN_DIR (a retried job, two people, a resubmitted RayJob) would each run
and store every episode, and each would delete the other's in-flight temporary files while
recovering from a crash on open. The driver takes ``flock(LOCK_EX | LOCK_NB)`` on the lock
file before it touches anything in the directory and writes its host, pid and start time into
it; a second driver is refused with who holds it.

Stale locks: the kernel drops a flock when its holder dies, SIGKILL included, so the lock of a
dead driver is free and the next driver takes it over; the file's stale contents only say who
held it last. On a shared filesystem: flock is honoured across hosts by NFSv4 (emulated with
POSIX locks by Linux since 2.6.12), CephFS and Lustre (mounted with ``flock``); where the
filesystem refuses flock (ENOLCK / EOPNOTSUPP) the driver falls back to the holder record
alone: it refuses a record of a live process on this host, and warns that a driver on another
host cannot be detected there.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import socket
import time
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError
from pipeline.rundir import LOCK_FILE

log = logging.getLogger("idr_eval.lock")


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


class RunDirLock:
    """``with RunDirLock(run_dir):`` holds the run directory for this driver (ConfigError if
    another driver holds it). Creates the directory if needed."""

    def __init__(self, run_dir: str | Path) -> None:
        self.run_dir = Path(run_dir)
        self.path = self.run_dir / LOCK_FILE
        self._fd: int | None = None
        self._created = False  # the run dir did not exist: removed again if the run wrote nothing

    def holder(self) -> dict[str, Any]:
        try:
            return json.loads(self.path.read_text() or "{}")
        except (OSError, ValueError):
            return {}

    def _refuse(self, holder: dict[str, Any]) -> ConfigError:
        who = (
            f"pid {holder.get('pid')} on host {holder.get('host')} since {holder.get('since')}"
            if holder
            else "another process"
        )
        return ConfigError(
            f"{self.run_dir} is in use by another idr-eval driver ({who}); two drivers on one "
            "run dir would run and store every episode twice. Wait for it to finish (or stop "
            "it), then run the same command again to resume; or choose another --out"
        )

    def acquire(self) -> None:
        import fcntl

        self._created = not self.run_dir.exists()
        self.run_dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            raise self._refuse(self.holder()) from None
        except OSError as e:
            if e.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                os.close(fd)
                raise
            self._check_record_only(e)
        record = {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "since": time.strftime("%FT%T%z"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(record).encode(), 0)
        os.fsync(fd)
        self._fd = fd

    def _check_record_only(self, err: OSError) -> None:
        holder = self.holder()
        same_host = holder.get("host") == socket.gethostname()
        pid = holder.get("pid")
        if same_host and pid not in (None, os.getpid()) and _pid_alive(int(pid)):
            raise self._refuse(holder)
        log.warning(
            "the filesystem of %s does not support flock (%s): a second driver on this host "
            "is refused by its pid, one on another host cannot be detected",
            self.run_dir,
            err.strerror,
        )

    def release(self) -> None:
        """Idempotent. The record is cleared (the file stays: removing it would race with a
        driver that opened it and waits to lock it)."""
        fd, self._fd = self._fd, None
        if fd is None:
            return
        try:
            os.ftruncate(fd, 0)
            if self._created and [p.name for p in self.run_dir.iterdir()] == [LOCK_FILE]:
                self.path.unlink()  # a run refused before writing anything leaves no dir
                self.run_dir.rmdir()
        finally:
            os.close(fd)  # drops the flock

    def __enter__(self) -> RunDirLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
