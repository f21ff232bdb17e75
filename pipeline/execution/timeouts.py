"""A wall-clock limit per episode (``executor.episode_timeout_s``).

Executor ``ray``: the scheduler kills the actor of an episode past its limit (a process kill
works whatever the episode is blocked in) and starts a fresh one. Executor ``inline`` has no
other process to kill, so :func:`alarm` arms SIGALRM and raises :class:`EpisodeTimeout` in
the episode's code. That works in the main thread only, on POSIX, and only where Python code
gets to run: a C call that never returns (a simulator stuck in a native loop) cannot be cut
off inline; use the ray executor for those.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

log = logging.getLogger("idr_eval.timeouts")


class EpisodeTimeout(BaseException):
    """The episode ran past ``executor.episode_timeout_s``.

    A BaseException so that the worker's ``except Exception`` (which turns episode errors
    into error rows) lets it through to the scheduler, which replaces the worker."""


def timeout_reason(seconds: float) -> str:
    return (
        f"EpisodeTimeout: the episode ran past executor.episode_timeout_s={seconds:g} s; "
        "its worker was replaced (raise the limit if episodes are legitimately this slow)"
    )


def alarm_supported() -> bool:
    return hasattr(signal, "setitimer") and threading.current_thread() is threading.main_thread()


@contextmanager
def alarm(seconds: float | None) -> Iterator[None]:
    """Raise EpisodeTimeout in this (main) thread after ``seconds``; no-op for None or where
    SIGALRM cannot be used (the caller checks :func:`alarm_supported` to warn once)."""
    if not seconds or not alarm_supported():
        yield
        return

    def fire(signum: int, frame: FrameType | None) -> None:
        raise EpisodeTimeout(f"episode ran past {seconds:g} s")

    previous = signal.signal(signal.SIGALRM, fire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
