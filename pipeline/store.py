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
"""

from __future__ import annotations

import os
import re
import uuid
from collections import defaultdict
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.errors import DiskFullError, is_disk_full
from workers.episode import EpisodeResult

EPISODE_SCHEMA = pa.schema(
    [
        ("run_id", pa.string()),
        ("cell_id", pa.string()),
        ("mode", pa.string()),
        ("guidance", pa.string()),
        ("strategy", pa.string()),
        ("alpha", pa.float64()),
        ("beta", pa.float64()),
        ("lam", pa.float64()),
        ("tau", pa.float64()),
        ("backbone", pa.string()),
        ("suite", pa.string()),
        ("task_id", pa.string()),
        ("task_name", pa.string()),
        ("instruction", pa.string()),
        ("episode_index", pa.int64()),
        ("seed", pa.int64()),
        ("init_state_id", pa.string()),
        ("success", pa.bool_()),
        ("steps", pa.int64()),
        ("success_step", pa.int64()),
        ("max_steps", pa.int64()),
        ("subtasks_done", pa.int64()),
        ("subtasks_total", pa.int64()),
        # failed episodes (error rows excluded): a code (timeout, or the env's own, e.g. the
        # tabletop chain's wrong_order / subtask_budget) and the env's words for it
        ("failure", pa.string()),
        ("failure_detail", pa.string()),
        ("sim_seconds", pa.float64()),
        ("wall_seconds", pa.float64()),
        ("inference_ms_mean", pa.float64()),
        ("gate_rate", pa.float64()),
        ("e_img_mean", pa.float64()),
        ("e_prop_mean", pa.float64()),
        ("r_img_mean", pa.float64()),
        ("error", pa.string()),
        ("attempt", pa.int64()),
        ("worker", pa.string()),
        ("node", pa.string()),  # HOSTNAME/RAY_NODE_ID of the actor (inline: the hostname)
        ("render_backend", pa.string()),
        ("crn", pa.bool_()),
        ("started_at", pa.string()),
        ("finished_at", pa.string()),
        ("code_version", pa.string()),
    ]
)

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

STEP_SCHEMA = pa.schema(
    [
        ("run_id", pa.string()),
        ("cell_id", pa.string()),
        ("task_id", pa.string()),
        ("episode_index", pa.int64()),
        ("inference_index", pa.int64()),
        ("step", pa.int64()),
        ("e_img", pa.float32()),
        ("e_prop", pa.float32()),
        ("r_img", pa.float32()),
        ("gate", pa.float32()),
        ("w_prop", pa.float32()),
        ("action_base", pa.list_(pa.float32())),
        ("action_final", pa.list_(pa.float32())),
        ("gripper", pa.float32()),
        ("inference_ms", pa.float32()),
    ]
)

KEY = ("cell_id", "task_id", "episode_index")
_BATCH_RE = re.compile(r"batch-(\d+)-([0-9a-f]+)\.parquet$")


def _safe(cell_id: str) -> str:
    return re.sub(r"[^A-Za-z0-9._=+-]", "_", cell_id)


def rows_to_table(rows: list[dict[str, Any]], schema: pa.Schema) -> pa.Table:
    """Rows -> table with exactly ``schema``; a row with a column the schema lacks is refused."""
    names = set(schema.names)
    for row in rows:
        extra = set(row) - names
        if extra:
            raise ValueError(f"row has columns not in the schema: {sorted(extra)}")
    return pa.Table.from_pylist(
        [{n: row.get(n) for n in schema.names} for row in rows], schema=schema
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
        if read_only:
            return
        for d in (self.episodes_dir, self.steps_dir):
            d.mkdir(parents=True, exist_ok=True)
        self._recover()

    # -- crash recovery --------------------------------------------------------------------
    def _recover(self) -> None:
        for tmp in self.run_dir.glob("*/cell=*/.*.tmp"):
            tmp.unlink()  # a write that never finished
        done = {
            p.relative_to(self.episodes_dir)
            for p in self.episodes_dir.glob("cell=*/batch-*.parquet")
        }
        for p in self.steps_dir.glob("cell=*/batch-*.parquet"):
            if p.relative_to(self.steps_dir) not in done:
                p.unlink()  # steps of a batch whose episodes never landed
        seqs = [int(m.group(1)) for p in done if (m := _BATCH_RE.search(p.name))]
        self._seq = max(seqs, default=0)

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
            by_cell[r.episode["cell_id"]].append(r)
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
        if not files:
            return schema.empty_table()
        return pa.concat_tables([pq.read_table(f, schema=schema) for f in files])

    def episodes(self) -> pa.Table:
        return self._read(self.episodes_dir, EPISODE_SCHEMA)

    def steps(self) -> pa.Table:
        return self._read(self.steps_dir, STEP_SCHEMA)

    def stored_count(self) -> int:
        files = self.episodes_dir.glob("cell=*/batch-*.parquet")
        return sum(pq.ParquetFile(f).metadata.num_rows for f in files)

    def stored_keys(self) -> set[tuple[str, str, int]]:
        t = self.episodes().select(list(KEY)).to_pydict()
        return set(zip(t["cell_id"], t["task_id"], t["episode_index"], strict=True))
