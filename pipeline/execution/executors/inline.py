"""One EpisodeWorker in the driver's process, without Ray (debugging, tests, 1-core boxes).

A hung episode is cut off with SIGALRM (pipeline.execution.timeouts): only in the main thread, and only
where Python code runs; a worker that timed out or ran out of memory is replaced by a fresh one.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

from pipeline.errors import RunError
from pipeline.execution.executors.base import ExecutorStats, Outcome
from pipeline.execution.timeouts import EpisodeTimeout, alarm, alarm_supported, timeout_reason
from workers.episode.rows import EpisodeSpec, WorkerSpec

log = logging.getLogger("idr_eval.executors.inline")


def episode_worker(spec: WorkerSpec) -> Any:
    """The episode worker of ``spec`` (workers.episode.worker, imported when the first one
    starts: it loads the simulators' and models' modules)."""
    from workers.episode.worker import EpisodeWorker

    return EpisodeWorker(spec)


class InlineExecutor:
    def __init__(
        self,
        worker_spec: WorkerSpec,
        episode_timeout_s: float | None = None,
        new_worker: Callable[[WorkerSpec], Any] = episode_worker,
    ) -> None:
        """``new_worker``: builds a worker from its spec (and a fresh one after a fault)."""
        self.new_worker = new_worker
        self.worker_spec = worker_spec
        self.limit = episode_timeout_s
        self.stats = ExecutorStats()
        self.worker: Any = None
        self._queued: EpisodeSpec | None = None

    def start(self, n_pending: int) -> None:
        if self.worker is not None or n_pending == 0:
            return
        t0 = time.monotonic()
        try:
            self.worker = self.new_worker(self.worker_spec)
        except Exception as exc:
            raise RunError(
                f"the worker cannot load: {type(exc).__name__}: {exc} (fix it and run the same "
                "command again)"
            ) from exc
        self.stats.workers = [self.worker.ping()]
        self.stats.startup_seconds = time.monotonic() - t0
        if self.limit and not alarm_supported():
            log.warning(
                "executor.episode_timeout_s=%g is not enforced: the inline executor needs the "
                "main thread for SIGALRM (use executor.kind=ray)",
                self.limit,
            )

    def free_slots(self) -> int:
        return int(self.worker is not None and self._queued is None)

    def in_flight(self) -> int:
        return int(self._queued is not None)

    def submit(self, spec: EpisodeSpec) -> None:
        if self.free_slots() == 0:
            raise RuntimeError("InlineExecutor.submit: no free slot (start it, then wait)")
        self._queued = spec

    def wait(self, timeout_s: float) -> list[Outcome]:
        """Runs the queued episode to its end (``timeout_s`` does not apply: one process)."""
        spec, self._queued = self._queued, None
        if spec is None:
            return []
        try:
            with alarm(self.limit):
                result = self.worker.run_episode(spec)
        except EpisodeTimeout:
            log.warning("episode %s timed out: replacing the worker", spec.key)
            self.stats.timeouts += 1
            self._replace()
            return [Outcome(spec, lost=timeout_reason(self.limit or 0), timed_out=True)]
        if result.unhealthy:
            self._replace()
        return [Outcome(spec, result=result)]

    def _replace(self) -> None:
        """A fresh EpisodeWorker (the old one may be mid-step or out of memory)."""
        try:
            self.worker.close()
        except Exception as exc:  # a broken worker may fail to close; it is dropped anyway
            log.warning("closing the old worker failed: %s", exc)
        self.stats.replaced += 1
        self.worker = self.new_worker(self.worker_spec)

    def close(self) -> None:
        worker, self.worker = self.worker, None
        if worker is not None:
            worker.close()
