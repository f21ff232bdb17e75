"""Compaction of a run's Parquet batches: a finished cell's many small batches merged into one
file, while the run goes on (after each flush) and on demand (``idr-eval compact``)."""

from __future__ import annotations

import logging
from collections.abc import Callable, Iterable

from pipeline.execution.signals import critical_section
from pipeline.results.store import RunStore
from workers.episode.rows import EpisodeResult

log = logging.getLogger("idr_eval.runner")


class CompactFinishedCells:
    """After each flush, compact the cells whose every episode is now stored: a long grid
    (cells run one after another) keeps one file per finished cell and table instead of one
    per batch, for its readers and for the key scan of a resume. Then calls ``then``."""

    def __init__(
        self,
        cells: list[str],
        per_cell: int,
        store: RunStore,
        stored_keys: Iterable[tuple[str, str, int]],
        then: Callable[[list[EpisodeResult]], None] | None = None,
    ) -> None:
        """``cells``: the run's cells, each of ``per_cell`` episodes when complete."""
        self.store, self.then = store, then
        stored: dict[str, int] = {}
        for cell, _, _ in stored_keys:
            stored[cell] = stored.get(cell, 0) + 1
        # cells complete at the start were compacted by the run that completed them
        self.remaining = {c: per_cell - stored.get(c, 0) for c in cells}

    def __call__(self, batch: list[EpisodeResult]) -> None:
        finished = []
        for result in batch:
            cell = result.episode.cell_id
            if cell in self.remaining:
                self.remaining[cell] -= 1
                if self.remaining[cell] == 0:
                    finished.append(cell)
        if finished:
            compact_run_dir(self.store, finished)
        if self.then is not None:
            self.then(batch)


def compact_run_dir(store: RunStore, cells: list[str] | None = None) -> dict[str, int]:
    """Merge each cell's batches (of ``cells``; None: all) into one file per table
    (pipeline.results.store: crash-safe), so that readers of a large run open one file per cell and
    table, not one per batch."""
    with critical_section():  # a signal waits: the compaction's removals are not interrupted
        merged = store.compact(cells)
    if merged:
        log.info(
            "compacted %d files of %d cells into one per cell and table",
            sum(merged.values()),
            len(merged),
        )
    return merged
