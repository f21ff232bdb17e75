"""The run's progress display: done/total, success so far, ETA."""

from __future__ import annotations

import logging
import sys
import time

log = logging.getLogger("idr_eval.progress")


class Progress:
    """done/total, success so far, ETA: a live bar on a terminal, log lines otherwise."""

    def __init__(self, total: int) -> None:
        self.total, self.t0, self._last = total, time.monotonic(), 0.0
        self._bar = None
        if total and sys.stderr.isatty():
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self._bar = Progress(
                TextColumn("[bold]episodes"),
                BarColumn(),
                TextColumn("{task.completed}/{task.total}"),
                TextColumn("{task.fields[info]}"),
                TimeRemainingColumn(),
            )
            self._task = self._bar.add_task("run", total=total, info="")
            self._bar.start()

    def update(self, done: int, successes: int, errors: int) -> None:
        info = f"success {successes}/{max(done - errors, 0)}  errors {errors}"
        if self._bar is not None:
            self._bar.update(self._task, completed=done, info=info)
            return
        now = time.monotonic()
        if now - self._last >= 5.0 or done == self.total:
            self._last = now
            rate = done / max(now - self.t0, 1e-9)
            eta = (self.total - done) / rate if rate > 0 else float("nan")
            log.info("episodes %d/%d  %s  eta %.0fs", done, self.total, info, eta)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
