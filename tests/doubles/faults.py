"""Faults the test doubles inject for real, for the fault tests (never in a real run).

- :func:`should_fire`: whether a fault set on some episodes fires now; with ``once_dir`` it
  fires once per run (an exclusive marker file shared by every process, so a retried episode
  on a fresh actor runs clean), otherwise every time.
- :func:`hang_forever`: a call that never returns (a wedged simulator or model server).
- :func:`exhaust_memory`: an allocation past an address-space limit (``RLIMIT_AS``) set just
  above what the process already maps: a genuine ``MemoryError``, as in a process out of
  memory; ``kill=True`` then delivers SIGKILL to the process, as the kernel's OOM killer or
  Ray's memory monitor would.
"""

from __future__ import annotations

import os
import signal
import time
from collections.abc import Collection
from pathlib import Path
from typing import NoReturn

MB = 2**20


def should_fire(
    fault: str, episode_index: int, episodes: Collection[int], once_dir: str | None
) -> bool:
    """True when ``episode_index`` is one of ``episodes`` (and, with ``once_dir``, the first time)."""
    if episode_index not in episodes:
        return False
    if once_dir is None:
        return True
    marker = Path(once_dir) / f"{fault}-{episode_index}"
    marker.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
    except FileExistsError:
        return False
    os.close(fd)
    return True


def hang_forever() -> NoReturn:
    """Never return (interruptible by signals, like most blocking calls)."""
    while True:
        time.sleep(3600)


def _mapped_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")


def exhaust_memory(limit_mb: int, kill: bool = False) -> NoReturn:
    """Allocate past RLIMIT_AS = (what the process maps now + ``limit_mb``); raise MemoryError.

    The soft limit is restored before raising, so the process stays usable (a fresh actor is
    what the scheduler gives the episode next). Linux only (reads /proc/self/statm)."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    mapped = _mapped_bytes()
    limit = mapped + limit_mb * MB
    want = 4 * limit_mb * MB
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        block = bytearray(want)
    except MemoryError:
        if kill:
            os.kill(os.getpid(), signal.SIGKILL)
        raise MemoryError(
            f"injected: allocating {want // MB} MB past RLIMIT_AS ({limit_mb} MB above the "
            f"{mapped // MB} MB this process maps) failed"
        ) from None
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))
    del block
    raise RuntimeError("RLIMIT_AS was not enforced: the allocation past it succeeded")
