"""SIGTERM / SIGINT stop a run cleanly: results flushed, files closed, MLflow runs KILLED.

:func:`stop_on_signals` (around a whole run, main thread) turns the first SIGTERM or SIGINT
into :class:`RunInterrupted`, a KeyboardInterrupt, raised where the driver is: the
scheduler's ``finally`` flushes the finished episodes, the runner marks the MLflow runs
KILLED, and ``idr-eval run`` on the same RUN_DIR resumes. Inside :func:`critical_section` (a
Parquet batch being written and recorded) the signal waits until the section ends, so a stop
never splits a batch from its bookkeeping. Further signals while stopping are ignored (the
stop is bounded: a flush, the report and MLflow); SIGKILL still stops the process at once,
and the atomic writes of the store leave no unreadable file then either.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType

log = logging.getLogger("idr_eval.signals")
HANDLED = (signal.SIGTERM, signal.SIGINT)


class RunInterrupted(KeyboardInterrupt):
    """The run was stopped by a signal; ``signum`` says which."""

    def __init__(self, signum: int) -> None:
        self.signum = signum
        super().__init__(f"stopped by {signal.Signals(signum).name}")

    @property
    def exit_code(self) -> int:
        return 128 + self.signum  # the shell's convention: 130 for SIGINT, 143 for SIGTERM


class _State:
    active = False  # handlers installed
    stopping = False  # RunInterrupted raised (or due): later signals are ignored
    depth = 0  # critical sections entered
    pending: int | None = None  # a signal that arrived inside a critical section
    received: int | None = None  # the signal that stops the run


def _handler(signum: int, frame: FrameType | None) -> None:
    if _State.stopping:
        log.warning("%s received while stopping: ignored", signal.Signals(signum).name)
        return
    _State.received = signum
    if _State.depth > 0:
        _State.pending = signum
        return
    _State.stopping = True
    raise RunInterrupted(signum)


@contextmanager
def stop_on_signals() -> Iterator[None]:
    """Install the handlers for the duration of a run (no-op outside the main thread)."""
    if threading.current_thread() is not threading.main_thread() or _State.active:
        yield
        return
    previous = {s: signal.signal(s, _handler) for s in HANDLED}
    _reset(active=True)
    try:
        yield
    except KeyboardInterrupt as e:
        # C extensions that check for signals (ray.wait) turn our exception into a plain
        # KeyboardInterrupt: give it back its signal
        if isinstance(e, RunInterrupted) or _State.received is None:
            raise
        raise RunInterrupted(_State.received) from None
    finally:
        for s, h in previous.items():
            signal.signal(s, h)
        _reset(active=False)


def _reset(active: bool) -> None:
    _State.active, _State.stopping, _State.depth = active, False, 0
    _State.pending = _State.received = None


def reinstall() -> None:
    """Put the handlers back after a library replaced them (``ray.init`` installs its own
    SIGTERM handler in the driver, which aborts the process)."""
    if _State.active and threading.current_thread() is threading.main_thread():
        for s in HANDLED:
            signal.signal(s, _handler)


@contextmanager
def critical_section() -> Iterator[None]:
    """Hold a signal until the block ends (then raise RunInterrupted), unless the block
    itself fails: that error wins and the run stops on it."""
    _State.depth += 1
    failed = False
    try:
        yield
    except BaseException:
        failed = True
        raise
    finally:
        _State.depth -= 1
        if _State.depth == 0 and _State.pending is not None:
            signum, _State.pending = _State.pending, None
            _State.stopping = True
            if not failed:
                raise RunInterrupted(signum)
