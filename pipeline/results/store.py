"""The run's tables in Parquet: fixed schemas, written only by the driver, crash-safe.

Layout of RUN_DIR::

    episodes/cell=<cell_id>/batch-<n>-<id>.parquet   one row per finished episode
    steps/cell=<cell_id>/batch-<n>-<id>.parquet      one row per inference of those episodes
    {episodes,steps}/cell=<cell_id>/compact-<n>-<id>.parquet   a cell's batches, merged

Each batch is written to a temporary name in the same directory and renamed into place
(``os.replace``), steps first, then episodes; a steps batch without its episodes batch (a
crash between the two renames) is removed when the store is opened. So a crash loses at most
the episodes in flight and never leaves an unreadable file, and a key
(cell_id, task_id, episode_index) is stored at most once: the episodes table is the record
of what is done, and resume skips its keys.

At the end of a run (and by ``idr-eval compact``) each cell's files are merged into one per
table (:meth:`RunStore.compact`), so that readers of a large run open a file per cell, not per
batch; a compacted episodes file lists in its Parquet metadata the files it merged, which
readers skip and the next writer removes, so a crash at any step of a compaction leaves each
key stored once. Readers scan the live files as one dataset, reading only the columns asked
for (resume reads the key columns only).

A batch that is unreadable anyway (a bad disk, a copy cut short by hand) is quarantined by the
next writer that opens the store: moved with its partner batch to ``RUN_DIR/quarantine/``, so
its keys count as not stored and resume re-runs them. Read-only openers skip such a file and
list it in ``unreadable``; they never move files.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import re
import uuid
from collections import defaultdict
from collections.abc import Iterable, Sequence
from pathlib import Path
from types import UnionType
from typing import Annotated, Any, Union, get_args, get_origin, get_type_hints

import pyarrow as pa
import pyarrow.dataset as ds
import pyarrow.parquet as pq

from pipeline.errors import DiskFullError, is_disk_full
from pipeline.rundir import EPISODES_DIR, QUARANTINE_DIR, STEPS_DIR, write_atomic
from workers.episode.rows import EpisodeResult, EpisodeRow, StepRow


def _arrow_type(hint: Any) -> pa.DataType:
    """A row field's type hint -> its Arrow type (``X | None`` is nullable, as every column)."""
    if get_origin(hint) is Annotated:
        base, *marks = get_args(hint)
        if base is float and "float32" in marks:
            return pa.float32()
        return _arrow_type(base)
    if get_origin(hint) in (UnionType, Union):
        (inner,) = [a for a in get_args(hint) if a is not type(None)]
        return _arrow_type(inner)
    if get_origin(hint) is list:
        return pa.list_(_arrow_type(get_args(hint)[0]))
    simple = {str: pa.string(), int: pa.int64(), float: pa.float64(), bool: pa.bool_()}
    if hint in simple:
        return simple[hint]
    raise TypeError(f"no Arrow type for the row field type {hint!r}")


def schema_of(row_type: type) -> pa.Schema:
    """The Parquet schema of a row dataclass: its fields, in order, with their Arrow types."""
    hints = get_type_hints(row_type, include_extras=True)
    return pa.schema([(f.name, _arrow_type(hints[f.name])) for f in dataclasses.fields(row_type)])


EPISODE_SCHEMA = schema_of(EpisodeRow)
STEP_SCHEMA = schema_of(StepRow)

# Episode columns that differ between two runs of the same config (timing, placement, run id);
# every other column is fixed by the config, the code and the (task, episode, seed) key.
VOLATILE_COLUMNS = (
    "wall_seconds",
    "inference_ms_mean",
    "worker",
    "node",
    "started_at",
    "finished_at",
    "run_id",
)

KEY = ("cell_id", "task_id", "episode_index")
log = logging.getLogger("idr_eval.store")
_BATCH_RE = re.compile(r"(batch|compact)-(\d+)-([0-9a-f]+)\.parquet$")
DATA_GLOB = "cell=*/*.parquet"  # batches and compacted files
COMPACT_PREFIX = "compact-"
SOURCES_KEY = b"idr_eval.sources"  # a compacted file's metadata: the files it merged
STEP_ROW_GROUP = 262_144  # rows per row group of a compacted steps file


def _safe(cell_id: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=+-]", "_", cell_id)


def rows_to_table(rows: Sequence[Any], schema: pa.Schema) -> pa.Table:
    """Typed rows (EpisodeRow / StepRow) -> a table with exactly ``schema``, column by column."""
    return pa.table(
        {
            n: pa.array([getattr(r, n) for r in rows], type=schema.field(n).type)
            for n in schema.names
        },
        schema=schema,
    )


class RunStore:
    """Parquet tables of one run directory."""

    def __init__(self, run_dir: str | Path, read_only: bool = False) -> None:
        """``read_only``: for readers (report, compare, figures) that may open a run directory
        while its driver is still writing: no crash recovery (which would delete a steps batch
        whose episodes batch is being renamed into place) and only complete batches are read."""
        self.run_dir = Path(run_dir)
        self.episodes_dir = self.run_dir / EPISODES_DIR
        self.steps_dir = self.run_dir / STEPS_DIR
        self.read_only = read_only
        self._seq = 0
        self.rows_written = 0
        # unreadable batches: moved to RUN_DIR/quarantine/ (writer) or skipped (read-only)
        self.quarantined: list[str] = []
        self.unreadable: list[str] = []
        if read_only:
            return
        for d in (self.episodes_dir, self.steps_dir):
            d.mkdir(parents=True, exist_ok=True)
        self._recover()

    # -- crash recovery --------------------------------------------------------------------
    def _recover(self) -> None:
        for tmp in self.run_dir.glob("*/cell=*/.*.tmp"):
            tmp.unlink()  # a write that never finished
        for rel in self.unreadable_files():
            if (self.run_dir / rel).exists():  # else quarantined just now with its partner
                self._quarantine(self.run_dir / rel)
        done = {p.relative_to(self.episodes_dir) for p in self.episodes_dir.glob(DATA_GLOB)}
        for p in self.steps_dir.glob(DATA_GLOB):
            if p.relative_to(self.steps_dir) not in done:
                p.unlink()  # steps of a batch (or compaction) whose episodes never landed
                log.info("removed %s: its episodes file never landed", p.relative_to(self.run_dir))
        stale = self._superseded()
        for root in (self.steps_dir, self.episodes_dir):
            for cell, name in sorted(stale):
                f = root / cell / name
                if f.exists():  # a compaction stopped before removing what it merged
                    f.unlink()
                    log.info(
                        "removed %s: merged into a compacted file", f.relative_to(self.run_dir)
                    )
        seqs = [int(m.group(2)) for p in done if (m := _BATCH_RE.search(p.name))]
        self._seq = max(seqs, default=0)

    def _superseded(self) -> set[tuple[str, str]]:
        """(cell dir, file name) of the batches and older compacted files that a compacted
        episodes file of the same cell holds (its Parquet metadata lists them)."""
        out: set[tuple[str, str]] = set()
        for c in self.episodes_dir.glob(f"cell=*/{COMPACT_PREFIX}*.parquet"):
            try:
                meta = pq.read_schema(c).metadata or {}
            except (OSError, pa.ArrowException):
                continue  # unreadable: quarantined by a writer, skipped by a reader
            cell = c.parent.name
            out.update((cell, n) for n in json.loads(meta.get(SOURCES_KEY, b"[]")))
        return out

    def _live(self, root: Path) -> list[Path]:
        """The files of ``root`` that hold stored rows: batches and compacted files, less what
        a compacted file supersedes (a compaction that stopped before removing its sources)."""
        stale = self._superseded()
        return [f for f in sorted(root.glob(DATA_GLOB)) if (f.parent.name, f.name) not in stale]

    def _quarantine(self, bad: Path) -> None:
        """Move an unreadable batch and its partner (the same batch of the other table) to
        RUN_DIR/quarantine/, so that its keys count as not stored and resume re-runs them."""
        rel = bad.relative_to(self.run_dir)
        part = Path(*rel.parts[1:])  # cell=<id>/batch-....parquet
        for root in (self.episodes_dir, self.steps_dir):
            src = root / part
            if src.exists():
                dst = self.run_dir / QUARANTINE_DIR / root.name / part
                dst.parent.mkdir(parents=True, exist_ok=True)
                os.replace(src, dst)
                self.quarantined.append(str(dst.relative_to(self.run_dir)))
        log.warning(
            "%s is unreadable: moved with its partner batch to %s/; its episodes run again",
            rel,
            QUARANTINE_DIR,
        )

    # -- writing -------------------------------------------------------------------------------
    @staticmethod
    def _write_atomic(table: pa.Table, path: Path, row_group_size: int | None = None) -> None:
        write_atomic(
            path,
            lambda tmp: pq.write_table(
                table, tmp, compression="zstd", row_group_size=row_group_size
            ),
            fsync=True,
        )

    def write(self, results: Iterable[EpisodeResult]) -> int:
        """Write finished episodes (one batch per cell). Returns the number of episodes written."""
        if self.read_only:
            raise RuntimeError(f"RunStore({self.run_dir}) was opened read-only")
        by_cell: dict[str, list[EpisodeResult]] = defaultdict(list)
        for r in results:
            by_cell[r.episode.cell_id].append(r)
        n = 0
        for cell_id, items in by_cell.items():
            self._seq += 1
            name = f"batch-{self._seq:06d}-{uuid.uuid4().hex[:8]}.parquet"
            part = f"cell={_safe(cell_id)}"
            episodes = rows_to_table([r.episode for r in items], EPISODE_SCHEMA)
            steps = rows_to_table([s for r in items for s in r.steps], STEP_SCHEMA)
            steps_path = self.steps_dir / part / name
            try:
                self._write_atomic(steps, steps_path)
                self._write_atomic(episodes, self.episodes_dir / part / name)
            except OSError as e:
                steps_path.unlink(missing_ok=True)  # no steps without their episodes
                if is_disk_full(e):
                    raise DiskFullError(
                        f"no space left on the device of {self.run_dir} while writing a batch of "
                        f"{len(items)} episodes ({e}); nothing partial was left and the "
                        f"{self.stored_count()} episodes stored before are intact: free space, "
                        "then run the same command again to resume"
                    ) from e
                raise
            n += len(items)
            self.rows_written += episodes.num_rows + steps.num_rows
        return n

    # -- compaction ----------------------------------------------------------------------------
    def compact(self, cells: Iterable[str] | None = None) -> dict[str, int]:
        """Merge each cell's files (of ``cells``, by cell id; None: every cell) into one per
        table; returns {cell dir: files merged}.

        Order, so that a kill at any point leaves every key stored once and every file
        readable: (1) the steps file is written (temporary name, fsync, rename): until its
        episodes partner lands it is an orphan, removed on open and ignored by readers;
        (2) the episodes file is written, naming in its metadata the files it merged: from
        this rename on, readers skip those, and the next open removes any left; (3) the merged
        files are removed. Only the run's driver (or ``idr-eval compact`` holding the lock)
        compacts."""
        if self.read_only:
            raise RuntimeError(f"RunStore({self.run_dir}) was opened read-only")
        done: dict[str, int] = {}
        wanted = None if cells is None else {f"cell={_safe(c)}" for c in cells}
        live = self._live(self.episodes_dir)
        for cell_dir in sorted(p for p in self.episodes_dir.glob("cell=*") if p.is_dir()):
            if wanted is not None and cell_dir.name not in wanted:
                continue
            files = [f for f in live if f.parent == cell_dir]
            if len(files) < 2:
                continue
            names = [f.name for f in files]
            episodes = pa.concat_tables(pq.read_table(f, schema=EPISODE_SCHEMA) for f in files)
            steps = pa.concat_tables(
                pq.read_table(self.steps_dir / cell_dir.name / n, schema=STEP_SCHEMA)
                for n in names
                if (self.steps_dir / cell_dir.name / n).is_file()
            )
            self._seq += 1
            name = f"{COMPACT_PREFIX}{self._seq:06d}-{uuid.uuid4().hex[:8]}.parquet"
            meta = {SOURCES_KEY: json.dumps(names).encode()}
            self._write_atomic(
                steps.replace_schema_metadata(meta),
                self.steps_dir / cell_dir.name / name,
                row_group_size=STEP_ROW_GROUP,
            )
            self._write_atomic(
                episodes.replace_schema_metadata(meta), cell_dir / name
            )  # the commit point
            for root in (self.steps_dir, self.episodes_dir):
                for n in names:
                    (root / cell_dir.name / n).unlink(missing_ok=True)
            done[cell_dir.name] = len(names)
        return done

    # -- reading -------------------------------------------------------------------------------
    def _read(
        self, root: Path, schema: pa.Schema, columns: Sequence[str] | None = None
    ) -> pa.Table:
        files = self._live(root)
        if self.read_only and root == self.steps_dir:  # a batch counts once its episodes landed
            files = [f for f in files if (self.episodes_dir / f.relative_to(root)).is_file()]
        out_schema = schema if columns is None else pa.schema([schema.field(c) for c in columns])
        if not files:
            return out_schema.empty_table()
        try:  # one parallel scan, only the columns asked for
            dataset = ds.dataset([str(f) for f in files], schema=schema, format="parquet")
            return dataset.to_table(columns=list(out_schema.names))
        except (OSError, pa.ArrowException):
            pass  # an unreadable file among them: file by file, to set it aside
        tables = []
        for f in files:
            try:
                tables.append(pq.read_table(f, schema=schema, columns=list(out_schema.names)))
            except FileNotFoundError:
                continue  # quarantined meanwhile with its partner
            except (OSError, pa.ArrowException) as e:
                if self.read_only:  # a reader never moves files: skipped, and said
                    log.warning("%s is unreadable (%s): skipped", f.relative_to(self.run_dir), e)
                    self.unreadable.append(str(f.relative_to(self.run_dir)))
                else:
                    self._quarantine(f)
        if not tables:
            return out_schema.empty_table()
        return pa.concat_tables(tables)

    def unreadable_files(self) -> list[str]:
        """Batches whose Parquet footer cannot be read (scans every file: for reports)."""
        bad = []
        for p in sorted(self.run_dir.glob(f"*/{DATA_GLOB}")):
            try:
                pq.read_metadata(p)
            except (OSError, pa.ArrowException):
                bad.append(str(p.relative_to(self.run_dir)))
        return bad

    def quarantined_files(self) -> list[str]:
        """Every file in RUN_DIR/quarantine/ (moved there by this or an earlier driver)."""
        q = self.run_dir / QUARANTINE_DIR
        return sorted(str(p.relative_to(self.run_dir)) for p in q.rglob("*.parquet"))

    def episodes(self, columns: Sequence[str] | None = None) -> pa.Table:
        return self._read(self.episodes_dir, EPISODE_SCHEMA, columns)

    def steps(self, columns: Sequence[str] | None = None) -> pa.Table:
        return self._read(self.steps_dir, STEP_SCHEMA, columns)

    def stored_count(self) -> int:
        n = 0
        for f in self._live(self.episodes_dir):
            try:
                n += pq.read_metadata(f).num_rows
            except (OSError, pa.ArrowException):
                continue  # unreadable: not stored (quarantined by the next writer)
        return n

    def stored_keys(self) -> set[tuple[str, str, int]]:
        t = self.episodes(columns=KEY).to_pydict()
        return set(zip(t["cell_id"], t["task_id"], t["episode_index"], strict=True))
