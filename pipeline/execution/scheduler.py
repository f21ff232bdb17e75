"""The scheduler: the retry and dedup policy between an executor and the store.

Every cell sees the same tasks, episode indices, seeds and so init states, so comparisons
between cells are paired. The scheduler feeds an executor (pipeline.execution.executors) the specs of a
stage that are not stored yet, keeping it full, and decides what each outcome means:

- a result: stored, unless its key is already stored or buffered (a call Ray ran twice is
  stored once: ``duplicates_dropped``); an error row (an exception inside the episode) is
  retried while attempts are left, the last one stored (never a task failure);
- lost (the worker died or timed out under it; the executor replaced it): retried while
  attempts are left, then stored as an error row made from the spec alone;
- requeued (its worker never came up): run again, not charged an attempt.

The runner owns the stages (the episodes, then tau calibration, then the calibrated cells):
:meth:`Scheduler.run_stage` runs one and may be called again on the same executor.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from pipeline.execution.executors import Executor, Outcome
from pipeline.execution.progress import Progress
from pipeline.execution.writer import BatchWriter
from workers.episode.rows import EpisodeResult, EpisodeRow, EpisodeSpec

log = logging.getLogger("idr_eval.scheduler")
WAIT_S = 1.0  # how long one wait for outcomes lasts (timeouts are checked in between)
LOOK_AHEAD = 256  # fresh specs read before starting the workers (at most this many start)


@dataclass
class RunSummary:
    total: int
    skipped: int = 0  # already stored (resume)
    stored: int = 0
    successes: int = 0
    errors: int = 0  # keys stored as error rows after max_attempts
    retries: int = 0
    actors_replaced: int = 0
    timeouts: int = 0  # episodes cut off at executor.episode_timeout_s
    duplicates_dropped: int = 0
    wall_seconds: float = 0.0
    startup_seconds: float = 0.0  # until the workers were ready (actors started, models loaded)
    workers: list[str] = field(default_factory=list)


class Scheduler:
    def __init__(
        self,
        executor: Executor,
        writer: BatchWriter,
        max_attempts: int,
        total: int,
        progress: Progress | None = None,
    ) -> None:
        """``total``: episodes of every stage of the run, for the summary and progress."""
        self.executor = executor
        self.writer = writer
        self.max_attempts = max_attempts
        self.progress = progress
        self.summary = RunSummary(total=total)
        self.pending: deque[EpisodeSpec] = deque()  # retries and requeues, before fresh specs
        self._t0 = time.monotonic()
        self._stored_elsewhere = 0  # by the writers of earlier stages run with their own
        self._started = False  # the executor starts when the first episode needs running

    def run_stage(
        self, specs: Iterable[EpisodeSpec], writer: BatchWriter | None = None
    ) -> RunSummary:
        """Run every spec not stored yet; return once each is stored (flushed). ``specs`` is
        walked once, as the executor has room (a lazy grid is never built whole).
        ``writer``: another store's for this stage (the held-out calibration episodes);
        None: the scheduler's own."""
        own = self.writer
        if writer is not None:
            self.writer = writer
            self._stored_elsewhere += own.stored  # still stored while another writer is busy
        source = iter(specs)
        try:
            while self._fill(source) or self.executor.in_flight():
                for outcome in self.executor.wait(WAIT_S):
                    self._handle(outcome)
                self._tick()
        finally:
            self.writer.flush()
            if writer is not None:
                self._stored_elsewhere += writer.stored - own.stored
                self.writer = own
            self._sync_stats()
            self._tick()
        return self.summary

    def _fill(self, source: Iterator[EpisodeSpec]) -> bool:
        """Submit retries first, then fresh specs (stored keys skipped), while the executor
        has room; False once nothing is left to submit."""
        while True:
            if not self.pending:
                spec = self._next_fresh(source)
                if spec is None:
                    return False
                self.pending.append(spec)
            if not self._started:  # as many workers as there are episodes to run, at most
                self._look_ahead(source)
                self.executor.start(len(self.pending))
                self._started = True
            if self.executor.free_slots() <= 0:
                return True
            self.executor.submit(self.pending.popleft())

    def _look_ahead(self, source: Iterator[EpisodeSpec]) -> None:
        """Pull up to LOOK_AHEAD fresh specs into the queue: how many workers are worth
        starting (a resume with one episode left starts one)."""
        while len(self.pending) < LOOK_AHEAD and (spec := self._next_fresh(source)):
            self.pending.append(spec)

    def _next_fresh(self, source: Iterator[EpisodeSpec]) -> EpisodeSpec | None:
        """The next spec of ``source`` not stored yet (stored ones counted as skipped)."""
        for spec in source:
            if not self.writer.holds(spec.key):
                return spec
            self.summary.skipped += 1
            if self.progress is not None:
                self.progress.eta.skipped(spec.task_id)
        return None

    # -- policy --------------------------------------------------------------------------------
    def _handle(self, outcome: Outcome) -> None:
        spec = outcome.spec
        if outcome.requeue:
            self.pending.appendleft(spec)
        elif outcome.result is not None:
            self._accept(spec, outcome.result)
        else:
            self._lost(spec, outcome.lost or "the worker gave no result")

    def _accept(self, spec: EpisodeSpec, result: EpisodeResult) -> None:
        if self.writer.holds(result.key):
            self.summary.duplicates_dropped += 1
            return
        if result.is_error and spec.attempt < self.max_attempts:
            self.summary.retries += 1
            log.warning(
                "episode %s attempt %d failed, retrying: %s",
                spec.key,
                spec.attempt,
                (result.episode.error or "").splitlines()[0],
            )
            self.pending.append(spec.retry())
            return
        self.summary.errors += int(result.is_error)
        self.summary.successes += int(result.episode.success and not result.is_error)
        self.writer.add(result)
        if self.progress is not None:
            self.progress.eta.finished(spec.task_id, result.episode.wall_seconds)

    def _lost(self, spec: EpisodeSpec, reason: str) -> None:
        """The worker died or timed out under this episode: retry, or store an error row."""
        if spec.attempt < self.max_attempts:
            log.warning(
                "episode %s attempt %d failed, retrying: %s", spec.key, spec.attempt, reason
            )
            self.summary.retries += 1
            self.pending.append(spec.retry())
            return
        self._accept(spec, EpisodeResult(EpisodeRow.error_row(spec, reason), []))

    # -- bookkeeping ---------------------------------------------------------------------------
    def _sync_stats(self) -> None:
        s, stats = self.summary, self.executor.stats
        s.stored = self.writer.stored + self._stored_elsewhere
        s.actors_replaced, s.timeouts = stats.replaced, stats.timeouts
        s.workers, s.startup_seconds = list(stats.workers), stats.startup_seconds
        s.wall_seconds = time.monotonic() - self._t0

    def _tick(self) -> None:
        if self.progress is not None:
            s = self.summary
            done = s.skipped + self.writer.stored + self._stored_elsewhere + self.writer.buffered
            self.progress.update(done, s.successes, s.errors, s.skipped)
