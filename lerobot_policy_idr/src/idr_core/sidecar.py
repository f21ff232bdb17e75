"""The diagnostics sidecar: one Parquet row per env of a batch per inference.

lerobot's dataset frames are fixed by the robot's features (extra keys are rejected), and
lerobot-eval does not hand a policy its output dir, so IDR's diagnostics go to a folder of
their own: ``part-NNNNN.parquet`` files, each written to a temporary name and renamed into
place, one per flush (at each episode's reset, every ``flush_every`` rows and at exit), so a
killed process leaves only whole files. ``idr-eval sidecar DIR`` reads them into the harness's
tables and figures.
"""

from __future__ import annotations

import atexit
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any

COLUMNS = (
    "episode",  # episode counter of this process (incremented at each policy reset)
    "tick",  # inference index within the episode
    "env",  # row of the batch (lerobot-eval's vectorized envs)
    "step",  # control step at which the chunk was requested (select_action calls so far)
    "wall_time",  # unix time at the end of the inference
    "mode",
    "forward_ms",  # the base network's forward (B rows, or 3B with IDR)
    "refine_ms",  # unnormalization, refinement and safety checks
    "inference_ms",  # whole predict_action_chunk
    "wait_ms",  # what the control loop waited for this chunk (select_action's time)
    "e_img",
    "e_prop",
    "r_img",
    "gate",
    "w_prop",
    "clipped",  # action elements clipped into the base's bounds
    "fallback",  # "" or why the base action was executed instead (nonfinite, deadline)
    "pass_rows",  # rows of the base's forward this env's inference cost (3 for IDR)
    "executed_steps",  # actions executed from its chunk (1 for temporal ensembling)
)

log = logging.getLogger(__name__)


def default_dir() -> Path:
    return Path.cwd() / "idr_diagnostics" / f"{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}"


class SidecarWriter:
    """Buffers rows and writes them as Parquet parts into ``directory``."""

    def __init__(self, directory: str | Path | None, flush_every: int = 256) -> None:
        self.dir = Path(directory) if directory else default_dir()
        self.flush_every = flush_every
        self._rows: list[dict[str, Any]] = []
        self._part = 0
        self._lock = threading.Lock()
        self._announced = False
        atexit.register(self._flush_at_exit)

    def add(self, rows: list[dict[str, Any]]) -> None:
        with self._lock:
            if not self._announced:
                self.dir.mkdir(parents=True, exist_ok=True)
                self._part = len(list(self.dir.glob("part-*.parquet")))
                log.warning("IDR diagnostics sidecar: %s", self.dir)
                self._announced = True
            self._rows.extend(rows)
            full = len(self._rows) >= self.flush_every
        if full:
            self.flush()

    def _flush_at_exit(self) -> None:
        try:
            self.flush()
        except OSError as e:  # the folder went away (a temporary dir): say so, no traceback
            log.warning("IDR diagnostics sidecar %s: last rows not written (%s)", self.dir, e)

    def flush(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        with self._lock:
            if not self._rows:
                return
            rows, self._rows = self._rows, []
            table = pa.Table.from_pylist([{c: r.get(c) for c in COLUMNS} for r in rows])
            final = self.dir / f"part-{self._part:05d}.parquet"
            self._part += 1
            tmp = final.with_name(f".{final.name}.tmp")
            pq.write_table(table, tmp)
            os.replace(tmp, final)


def read_sidecar(directory: str | Path):
    """All rows of a sidecar folder as one pandas DataFrame (parts in order)."""
    import pandas as pd
    import pyarrow.parquet as pq

    parts = sorted(Path(directory).glob("part-*.parquet"))
    if not parts:
        raise FileNotFoundError(
            f"{directory}: no part-*.parquet files; is it an IDR diagnostics folder (the "
            "policy's diagnostics_dir, said at the start of a rollout)?"
        )
    return pd.concat([pq.read_table(p).to_pandas() for p in parts], ignore_index=True)
