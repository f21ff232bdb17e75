"""An executor whose outcomes a test scripts: the scheduler's policy without any worker."""

from __future__ import annotations

from collections.abc import Callable

from pipeline.execution.executors import ExecutorStats, Outcome
from workers.episode.rows import EpisodeSpec

# spec -> the outcomes the executor reports for it (several: a call Ray answered twice)
Script = Callable[[EpisodeSpec], list[Outcome]]


class ScriptedExecutor:
    def __init__(self, script: Script, slots: int = 2) -> None:
        self.script = script
        self.slots = slots
        self.stats = ExecutorStats()
        self.submitted: list[EpisodeSpec] = []
        self._queue: list[EpisodeSpec] = []
        self.started = self.closed = False

    def start(self, n_pending: int) -> None:
        self.started = True
        self.stats.workers = ["scripted"]

    def free_slots(self) -> int:
        return self.slots - len(self._queue)

    def in_flight(self) -> int:
        return len(self._queue)

    def submit(self, spec: EpisodeSpec) -> None:
        assert self.free_slots() > 0, "submitted past free_slots()"
        self.submitted.append(spec)
        self._queue.append(spec)

    def wait(self, timeout_s: float) -> list[Outcome]:
        queue, self._queue = self._queue, []
        return [o for spec in queue for o in self.script(spec)]

    def close(self) -> None:
        self.closed = True
