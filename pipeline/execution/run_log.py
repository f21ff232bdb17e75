"""What a run shows on the terminal, and where the rest goes.

The terminal is the run's other face: its plan (cells x tasks x episodes), one progress line
with an ETA, warnings and errors of idr-eval, and the report. Everything else is kept in the
run dir, under ``logs/``:

- ``driver.log``: every log record of the driver at INFO and above (DEBUG with ``-v``):
  idr-eval's own and the libraries' (Ray's start-up and token-authentication lines, MLflow's
  database set-up), whose own handlers would print them on the terminal. A library's ERROR
  still reaches the terminal too.
- ``worker-<pid>.log`` / ``policy-<pid>.log``: what each Ray actor process prints, Python and C
  libraries alike (robosuite's macro warnings, checkpoint loading, an env server's output), by
  :func:`workers.worker_log.log_to_file`; Ray no longer streams the actors' output to the
  terminal. On a cluster node that does not see the run dir, an actor's output stays in Ray's
  worker logs (``ray logs``).

Records logged before the run dir is known (Ray starts before anything is written to it) are
held in memory and written once it is.
"""

from __future__ import annotations

import logging
import logging.handlers
import sys
from pathlib import Path

from pipeline.rundir import LOGS_DIR

DRIVER_LOG = "driver.log"
#: Libraries that install their own terminal handlers: rerouted to the run's log.
LIBRARY_LOGGERS = ("ray", "mlflow", "alembic")
_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"


class _ConsoleFilter(logging.Filter):
    """idr-eval's records at the console level; any other logger's at WARNING and above."""

    def __init__(self, level: int) -> None:
        super().__init__()
        self.level = level

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name == "idr_eval" or record.name.startswith("idr_eval."):
            return record.levelno >= self.level
        return record.levelno >= logging.WARNING


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever ``sys.stderr`` is at the time: a live progress bar replaces it to
    print records above the bar instead of through it."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property  # type: ignore[override]
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value) -> None:
        pass


class RunLog:
    """The driver's logging: a quiet terminal, and everything in RUN_DIR/logs/driver.log."""

    def __init__(self) -> None:
        self.console: logging.Handler | None = None
        self.buffer: logging.handlers.MemoryHandler | None = None
        self.file: logging.Handler | None = None
        self.run_dir: Path | None = None

    def install(self, verbose: bool = False) -> None:
        """Terminal handler plus an in-memory buffer for the run's log file (until
        :meth:`attach`); libraries already imported are rerouted now, the others when
        :meth:`route_libraries` is called after their import."""
        root = logging.getLogger()
        root.setLevel(logging.DEBUG if verbose else logging.INFO)
        self.console = _StderrHandler()
        self.console.setFormatter(logging.Formatter(_FORMAT, "%H:%M:%S"))
        self.console.addFilter(_ConsoleFilter(logging.DEBUG if verbose else logging.INFO))
        # flushLevel above CRITICAL: held until a target exists, whatever the level
        self.buffer = logging.handlers.MemoryHandler(100_000, flushLevel=logging.CRITICAL + 1)
        self.buffer.setFormatter(logging.Formatter(_FORMAT))
        root.handlers = [self.console, self.buffer]
        self.route_libraries()

    def route_libraries(self) -> None:
        """Send the libraries' records to the run's log (and their errors to the terminal)
        instead of their own terminal handlers; for a library imported after :meth:`install`,
        call again once it is (``import ray`` installs its handler)."""
        if self.buffer is None:
            return
        errors = _StderrHandler()
        errors.setLevel(logging.ERROR)
        errors.setFormatter(logging.Formatter(_FORMAT, "%H:%M:%S"))
        for name in LIBRARY_LOGGERS:
            lg = logging.getLogger(name)
            lg.handlers = [self.file or self.buffer, errors]
            lg.propagate = False

    def attach(self, run_dir: Path) -> Path | None:
        """Write the log to RUN_DIR/logs/driver.log from now on (what was held, first)."""
        if self.buffer is None or self.run_dir == run_dir:
            return None
        logs = run_dir / LOGS_DIR
        logs.mkdir(parents=True, exist_ok=True)
        self.file = logging.FileHandler(logs / DRIVER_LOG, encoding="utf-8")
        self.file.setFormatter(logging.Formatter(_FORMAT))
        self.buffer.setTarget(self.file)
        self.buffer.flush()
        root = logging.getLogger()
        root.handlers = [h for h in root.handlers if h is not self.buffer] + [self.file]
        self.route_libraries()
        self.run_dir = run_dir
        return logs / DRIVER_LOG


#: The CLI's run log; ``attach`` and ``route_libraries`` are no-ops where it is not installed
#: (a library user, the tests).
RUN_LOG = RunLog()
