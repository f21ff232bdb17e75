"""A wall-clock limit per episode (``executor.episode_timeout_s``).

Executor ``ray``: the scheduler kills the actor of an episode past its limit (a process kill
works whatever the episode is blocked in) and starts a fresh one. Executor ``inline`` has no
other process to kill, so :func:`alarm` sends SIGALRM to the main thread and raises :class:`EpisodeTimeout` in
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
    return hasattr(signal, "pthread_kill") and threading.current_thread() is threading.main_thread()


@contextmanager
def alarm(seconds: float | None) -> Iterator[None]:
    """Raise EpisodeTimeout in this (main) thread after ``seconds``; no-op for None or where
    SIGALRM cannot be used (the caller checks :func:`alarm_supported` to warn once).

    The signal is sent to the main thread itself (``pthread_kill`` from a timer thread), with
    SIGALRM unblocked there for the duration. A process-wide timer (``setitimer``) lets the
    kernel deliver SIGALRM to any thread that does not block it (a library's native worker
    thread, for one); the main thread's blocking call is then not interrupted, and the
    handler runs only when that call returns on its own, which for a hung call is never."""
    if not seconds or not alarm_supported():
        yield
        return

    def fire(signum: int, frame: FrameType | None) -> None:
        raise EpisodeTimeout(f"episode ran past {seconds:g} s")

    main = threading.main_thread().ident
    assert main is not None
    timer = threading.Timer(seconds, signal.pthread_kill, (main, signal.SIGALRM))
    timer.daemon = True
    previous = signal.signal(signal.SIGALRM, fire)
    blocked = signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGALRM})
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        signal.signal(signal.SIGALRM, previous)
        if signal.SIGALRM in blocked:
            signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
