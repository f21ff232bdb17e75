"""Finished episodes -> the store, in small batches; the one record of which keys are done.

Results are buffered and written ``flush_every`` at a time (one Parquet batch per cell), each
write inside a critical section: a SIGTERM waits until the batch is written and recorded, so a
stopped run never leaves a key half-stored. ``on_flush`` sees each written batch (MLflow
progress).
"""

from __future__ import annotations

from collections.abc import Callable

from pipeline.execution.signals import critical_section
from pipeline.results.store import RunStore
from workers.episode.rows import EpisodeResult


class BatchWriter:
    def __init__(
        self,
        store: RunStore,
        flush_every: int,
        on_flush: Callable[[list[EpisodeResult]], None] | None = None,
        check_dir: Callable[[], None] | None = None,
        stored_keys: set[tuple[str, str, int]] | None = None,
    ) -> None:
        """``check_dir``: raises when the run directory is no longer the one this run writes
        (checked before each batch, so a deleted directory is never silently recreated).
        ``stored_keys``: the store's keys where the caller read them already."""
        self.store = store
        self.check_dir = check_dir
        self.flush_every = flush_every
        self.on_flush = on_flush
        self.stored_keys = stored_keys if stored_keys is not None else store.stored_keys()
        self.stored = 0  # written by this writer
        self._buffer: list[EpisodeResult] = []
        self._buffered: set[tuple[str, str, int]] = set()

    def holds(self, key: tuple[str, str, int]) -> bool:
        """Whether ``key`` is stored or waiting in the buffer (a second result is a duplicate)."""
        return key in self.stored_keys or key in self._buffered

    @property
    def buffered(self) -> int:
        return len(self._buffer)

    def add(self, result: EpisodeResult) -> None:
        self._buffer.append(result)
        self._buffered.add(result.key)
        if len(self._buffer) >= self.flush_every:
            self.flush()

    def flush(self) -> None:
        if not self._buffer:
            return
        with critical_section():  # a SIGTERM waits until the batch is written and recorded
            # taken out first: a batch that fails to write (a full disk) is not tried again
            # by the flush at the end of the run; its episodes run again on resume
            batch, self._buffer, self._buffered = self._buffer, [], set()
            if self.check_dir is not None:
                self.check_dir()
            self.store.write(batch)
            self.stored_keys.update(r.key for r in batch)
            self.stored += len(batch)
        if self.on_flush is not None:
            self.on_flush(batch)
