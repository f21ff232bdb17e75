"""The two kinds of error a user sees: bad input (:class:`ConfigError`, found before any work
starts) and faults met while running (:class:`RunError`: a full disk, a signal). Both reach
the user as one line naming the fix, never a traceback (``idr-eval`` exits 2 for a ConfigError, 1 for a RunError).
"""

from __future__ import annotations

import errno

_NO_SPACE = {errno.ENOSPC, errno.EDQUOT}


class ConfigError(ValueError):
    """A config or override is invalid; the message names the field and the fix."""


class RunError(RuntimeError):
    """The run stopped on a fault; the message says what happened and how to go on."""


class DiskFullError(RunError):
    """No space left where the run writes; what was stored before is intact."""


class AllEpisodesFailedError(RunError):
    """Every episode of the run ended as an error row: the run measured nothing."""


class RunDirLostError(RunError):
    """The run directory lost its files while the run wrote to it (deleted, unmounted)."""


def is_disk_full(exc: BaseException) -> bool:
    """ENOSPC / EDQUOT, also when it comes from pyarrow (which may not set errno)."""
    if not isinstance(exc, OSError):
        return False
    return exc.errno in _NO_SPACE or "No space left on device" in str(exc)
