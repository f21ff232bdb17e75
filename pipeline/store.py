"""The run's tables in Parquet: fixed schemas, written only by the driver, crash-safe.

Layout of RUN_DIR::

    episodes/cell=<cell_id>/batch-<n>-<id>.parquet   one row per finished episode
    steps/cell=<cell_id>/batch-<n>-<id>.parquet      one row per inference of those episodes

Each batch is written to a temporary name in the same directory and renamed into place
(``os.replace``), steps first, then episodes; a steps batch without its episodes batch (a
crash between the two renames) is removed when the store is opened. So a crash loses at most
the episodes in flight and never leaves an unreadable file, and a key
(cell_id, task_id, episode_index) is stored at most once: the episodes table is the record
of what is done, and resume skips its keys.

A batch that is unreadable anyway (a bad disk, a copy cut short by hand) is quarantined by the
next writer that opens the store: moved with its partner batch to ``RUN_DIR/quarantine/``, so
its keys count as not stored and resume re-runs them. Read-only openers skip such a file and
list it in ``unreadable``; they never move files.
"""

from __future__ import annotations

import dataclasses
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
import pyarrow.parquet as pq

from pipeline.errors import DiskFullError, is_disk_full
from workers.episode import EpisodeResult, EpisodeRow, StepRow


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
QUARANTINE_DIR = "quarantine"
log = logging.getLogger("idr_eval.store")
_BATCH_RE = re.compile(r"batch-(\d+)-([0-9a-f]+)\.parquet$")


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
        self.episodes_dir = self.run_dir / "episodes"
        self.steps_dir = self.run_dir / "steps"
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
        for p in sorted(self.run_dir.glob("*/cell=*/batch-*.parquet")):
            try:
                pq.read_metadata(p)
            except FileNotFoundError:
                continue  # quarantined just now with its partner
            except (OSError, pa.ArrowException):
                self._quarantine(p)
        done = {
            p.relative_to(self.episodes_dir)
            for p in self.episodes_dir.glob("cell=*/batch-*.parquet")
        }
        for p in self.steps_dir.glob("cell=*/batch-*.parquet"):
            if p.relative_to(self.steps_dir) not in done:
                p.unlink()  # steps of a batch whose episodes never landed
        seqs = [int(m.group(1)) for p in done if (m := _BATCH_RE.search(p.name))]
        self._seq = max(seqs, default=0)

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
    def _write_atomic(table: pa.Table, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        try:
            pq.write_table(table, tmp, compression="zstd")
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
            os.replace(tmp, path)
            dir_fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)  # the rename itself survives a power cut
            finally:
                os.close(dir_fd)
        finally:
            if tmp.exists():
                tmp.unlink()

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

    # -- reading -------------------------------------------------------------------------------
    def _read(self, root: Path, schema: pa.Schema) -> pa.Table:
        files = sorted(root.glob("cell=*/batch-*.parquet"))
        if self.read_only and root == self.steps_dir:  # a batch counts once its episodes landed
            files = [f for f in files if (self.episodes_dir / f.relative_to(root)).is_file()]
        tables = []
        for f in files:
            try:
                tables.append(pq.read_table(f, schema=schema))
            except FileNotFoundError:
                continue  # quarantined meanwhile with its partner
            except (OSError, pa.ArrowException) as e:
                if self.read_only:  # a reader never moves files: skipped, and said
                    log.warning("%s is unreadable (%s): skipped", f.relative_to(self.run_dir), e)
                    self.unreadable.append(str(f.relative_to(self.run_dir)))
                else:
                    self._quarantine(f)
        if not tables:
            return schema.empty_table()
        return pa.concat_tables(tables)

    def unreadable_files(self) -> list[str]:
        """Batches whose Parquet footer cannot be read (scans every file: for reports)."""
        bad = []
        for p in sorted(self.run_dir.glob("*/cell=*/batch-*.parquet")):
            try:
                pq.read_metadata(p)
            except (OSError, pa.ArrowException):
                bad.append(str(p.relative_to(self.run_dir)))
        return bad

    def quarantined_files(self) -> list[str]:
        """Every file in RUN_DIR/quarantine/ (moved there by this or an earlier driver)."""
        q = self.run_dir / QUARANTINE_DIR
        return sorted(str(p.relative_to(self.run_dir)) for p in q.rglob("*.parquet"))

    def episodes(self) -> pa.Table:
        return self._read(self.episodes_dir, EPISODE_SCHEMA)

    def steps(self) -> pa.Table:
        return self._read(self.steps_dir, STEP_SCHEMA)

    def stored_count(self) -> int:
        n = 0
        for f in self.episodes_dir.glob("cell=*/batch-*.parquet"):
            try:
                n += pq.read_metadata(f).num_rows
            except (OSError, pa.ArrowException):
                continue  # unreadable: not stored (quarantined by the next writer)
        return n

    def stored_keys(self) -> set[tuple[str, str, int]]:
        t = self.episodes().select(list(KEY)).to_pydict()
        return set(zip(t["cell_id"], t["task_id"], t["episode_index"], strict=True))
