"""An actor's output into the run dir: ``RUN_DIR/logs/<role>-<pid>.log``.

Ray streams what an actor prints to the driver's terminal, where robosuite's macro warnings,
checkpoint loading lines and the like drown the run's progress. Each actor process instead
sends its file descriptors 1 and 2 to its own file in the run dir (pipeline.execution.run_log says what
goes where): Python's and C libraries' output alike, and that of the processes it starts (an
env server inherits them). Only inside a Ray actor: the inline executor runs episodes in the
driver, whose terminal stays its own. On a node that does not see the run dir (a cluster
without a shared file system), the output stays in Ray's worker logs.
"""

from __future__ import annotations

import contextlib
import os
import sys
from datetime import UTC, datetime
from pathlib import Path


def in_ray_actor() -> bool:
    ray = sys.modules.get("ray")
    if ray is None or not ray.is_initialized():
        return False
    try:
        return ray.get_runtime_context().get_actor_id() is not None
    except Exception:  # an old or partial Ray
        return False


def log_to_file(log_dir: str | None, role: str) -> Path | None:
    """Send this actor process's fds 1 and 2 to ``log_dir/<role>-<pid>.log`` (appended);
    None (nothing changed) outside a Ray actor or where ``log_dir`` is not visible."""
    if not log_dir or not in_ray_actor() or not Path(log_dir).is_dir():
        return None
    path = Path(log_dir) / f"{role}-{os.getpid()}.log"
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    except OSError:
        return None
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(OSError, ValueError):
            stream.flush()
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    stamp = datetime.now(UTC).isoformat(timespec="seconds")
    print(f"--- {role} pid {os.getpid()} on {os.uname().nodename}, {stamp}", flush=True)
    return path
