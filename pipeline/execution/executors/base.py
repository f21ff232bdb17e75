"""What every executor is: the :class:`Executor` protocol, its :class:`Outcome` and stats."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

from workers.episode.rows import EpisodeResult, EpisodeSpec


@dataclass(frozen=True)
class Outcome:
    """What became of one submitted episode. Exactly one of:

    - ``result``: the worker returned rows (an error row too, for an exception inside it);
    - ``lost``: no result, the worker died or timed out under it (``timed_out``) and was
      replaced; the reason, for the error row if no attempt is left;
    - ``requeue``: handed back before it started (its worker never came up), not an attempt.
    """

    spec: EpisodeSpec
    result: EpisodeResult | None = None
    lost: str | None = None
    timed_out: bool = False
    requeue: bool = False


@dataclass
class ExecutorStats:
    workers: list[str] = field(default_factory=list)  # ids of the workers first started
    startup_seconds: float = 0.0  # until they were ready (processes up, models loaded)
    replaced: int = 0  # workers replaced (died, out of memory, timed out)
    timeouts: int = 0  # episodes cut off at executor.episode_timeout_s


class Executor(Protocol):
    stats: ExecutorStats

    def start(self, n_pending: int) -> None:
        """Start the workers (no more than there are episodes pending); idempotent."""

    def free_slots(self) -> int:
        """How many more episodes can be submitted now."""

    def in_flight(self) -> int:
        """Episodes submitted whose outcome has not been returned by :meth:`wait` yet."""

    def submit(self, spec: EpisodeSpec) -> None: ...

    def wait(self, timeout_s: float) -> list[Outcome]:
        """Outcomes ready within ``timeout_s`` (possibly none); runs timeouts and replacements."""

    def close(self) -> None:
        """Stop every worker; idempotent. No worker outlives the run."""
