"""The run's progress display: done/total, success so far, ETA.

The ETA is measured, per task: the episodes left of each task times the mean wall time of
that task's finished episodes (a task not seen yet: the mean over all), spread over the
executor's slots. Episodes of one benchmark differ by an order of magnitude in length (the
tabletop's organize runs up to 1000 steps, pick_color 120), so a rate of episodes per second
taken over the first, short tasks would promise an end long before it comes. Until the
first episode ends there is no measurement, and the ETA says so instead of guessing.
"""

from __future__ import annotations

import logging
import sys
import time

log = logging.getLogger("idr_eval.progress")
LOG_EVERY_S = 15.0  # without a terminal: one line at most this often (and at the end)


def _clock(seconds: float) -> str:
    s = round(seconds)
    return (
        f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"
    )


class EtaModel:
    """Remaining wall time from the finished episodes' times, per task."""

    def __init__(self, per_task: dict[str, int], slots: int) -> None:
        self.left = dict(per_task)  # episodes not finished yet, per task
        self.slots = max(int(slots), 1)
        self._sum: dict[str, float] = {}
        self._n: dict[str, int] = {}
        self._warm: tuple[dict[str, float], dict[str, int]] = ({}, {})
        self._timed = 0

    def skipped(self, task: str) -> None:
        """An episode stored by an earlier run (resume): no time measured, none left."""
        self.left[task] = max(self.left.get(task, 0) - 1, 0)

    def finished(self, task: str, wall_seconds: float | None) -> None:
        self.left[task] = max(self.left.get(task, 0) - 1, 0)
        if wall_seconds is None or wall_seconds < 0:
            return
        # the first episode of each slot also pays its worker's start (scene build, model
        # warm-up): kept apart, used only while nothing else is measured
        into = self._warm if self._timed < self.slots else (self._sum, self._n)
        self._timed += 1
        into[0][task] = into[0].get(task, 0.0) + wall_seconds
        into[1][task] = into[1].get(task, 0) + 1

    def seconds(self) -> float | None:
        """Seconds to the end; None before any episode was timed."""
        if not sum(self.left.values()):
            return 0.0
        sums, counts = (self._sum, self._n) if self._n else self._warm
        n = sum(counts.values())
        if n == 0:
            return None
        overall = sum(sums.values()) / n
        work = sum(
            left * (sums[t] / counts[t] if counts.get(t) else overall)
            for t, left in self.left.items()
        )
        parallel = min(self.slots, max(sum(self.left.values()), 1))
        return work / parallel


class Progress:
    """done/total, success so far, ETA: a live line on a terminal, a log line otherwise.

    ``per_task``: episodes of each task over every stage (for the ETA); ``slots``: episodes
    the executor runs at once."""

    def __init__(self, total: int, per_task: dict[str, int] | None = None, slots: int = 1) -> None:
        self.total, self.t0, self._last, self._ended = total, time.monotonic(), 0.0, False
        self.eta = EtaModel(per_task or {}, slots)
        self._bar = None
        if total and sys.stderr.isatty():
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self._bar = Progress(
                TextColumn("[bold]episodes"),
                BarColumn(),
                TextColumn("{task.completed}/{task.total}"),
                TextColumn("{task.fields[info]}"),
                TimeElapsedColumn(),
                transient=False,
            )
            self._task = self._bar.add_task("run", total=total, info="")
            self._bar.start()

    def _eta_text(self, done: int) -> str:
        if done >= self.total:
            return "done"
        seconds = self.eta.seconds()
        return "eta: after the first episode" if seconds is None else f"eta {_clock(seconds)}"

    def update(self, done: int, successes: int, errors: int, skipped: int = 0) -> None:
        """``done`` counts the episodes an earlier run stored (``skipped``, on resume); the
        success rate is over the episodes this run finished, whose successes it counted."""
        finished = max(done - skipped - errors, 0)
        resumed = f"  ({skipped} stored before)" if skipped else ""
        info = f"success {successes}/{finished}  errors {errors}{resumed}  {self._eta_text(done)}"
        if self._bar is not None:
            self._bar.update(self._task, completed=done, info=info)
            return
        now = time.monotonic()
        if self._ended or not done:
            return
        if now - self._last >= LOG_EVERY_S or done == self.total:
            self._last, self._ended = now, done == self.total  # the final line once
            log.info("episodes %d/%d  %s", done, self.total, info)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
