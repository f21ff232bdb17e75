"""Compaction: a cell's batches merged into one file per table, crash-safe at every step, and
read alike by every reader before and after."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipeline.results.store import KEY, SOURCES_KEY, RunStore
from tests.doubles.rows import result

ROOT = Path(__file__).resolve().parents[3]


def _fill(run_dir: Path, batches: int = 3) -> None:
    """``batches`` batches per cell, 2 cells, 2 episodes each, 3 inferences per episode."""
    store = RunStore(run_dir)
    i = 0
    for _ in range(batches):
        rs = []
        for cell in ("baseline", "E"):
            for _ in range(2):
                ep = {"cell_id": cell, "task_id": "t", "episode_index": i, "success": i % 3 == 0}
                steps = [
                    {
                        "cell_id": cell,
                        "task_id": "t",
                        "episode_index": i,
                        "inference_index": k,
                        "e_img": float(i + k),
                        "action_base": [0.1 * k, 0.2],
                    }
                    for k in range(3)
                ]
                rs.append(result(ep, steps))
                i += 1
        store.write(rs)


def _tables(run_dir: Path) -> tuple[list[dict], list[dict]]:
    store = RunStore(run_dir, read_only=True)
    order = [*KEY]
    eps = store.episodes().to_pandas().sort_values(order).reset_index(drop=True)
    steps = (
        store.steps().to_pandas().sort_values([*order, "inference_index"]).reset_index(drop=True)
    )
    return eps.astype(str).to_dict("records"), steps.astype(str).to_dict("records")


def test_compaction_keeps_every_row_in_one_file_per_cell_and_table(tmp_path) -> None:
    _fill(tmp_path)
    before = _tables(tmp_path)
    assert len(list(tmp_path.rglob("*.parquet"))) == 2 * 2 * 3
    merged = RunStore(tmp_path).compact()
    assert merged == {"cell=E": 3, "cell=baseline": 3}
    files = sorted(p.relative_to(tmp_path) for p in tmp_path.rglob("*.parquet"))
    assert len(files) == 4 and all(p.name.startswith("compact-") for p in files)
    assert _tables(tmp_path) == before
    meta = pq.read_schema(tmp_path / files[0]).metadata
    assert len(json.loads(meta[SOURCES_KEY])) == 3
    _fill(tmp_path, batches=1)  # new batches next to a compacted file: merged with it
    assert RunStore(tmp_path).compact() == {"cell=E": 2, "cell=baseline": 2}
    assert RunStore(tmp_path, read_only=True).stored_count() == 16


KILLER = """
import os, pathlib, signal, sys
from pipeline.results import store as S
k, n = int(sys.argv[2]), [0]
def step():
    if n[0] == k:
        os.kill(os.getpid(), signal.SIGKILL)
    n[0] += 1
real_replace, real_unlink = os.replace, pathlib.Path.unlink
def replace(a, b):
    step(); real_replace(a, b)
def unlink(self, missing_ok=False):
    if self.suffix == ".parquet" and not self.name.startswith("."):
        step()
    real_unlink(self, missing_ok=missing_ok)
S.os.replace = replace
pathlib.Path.unlink = unlink
S.RunStore(sys.argv[1]).compact()
print("finished", n[0])
"""


@pytest.mark.parametrize("kill_at", [0, 1, 2, 5, 7, 8, 9, 12, 16])
def test_a_kill_at_any_step_leaves_every_key_once(tmp_path, kill_at, caplog) -> None:
    """SIGKILL of the compacting process before its k-th rename or removal (k = 0: before the
    steps file lands; 1: before the episodes file, the commit; then the removals): every reader
    sees each key once, every file is readable, and the next open finishes the job."""
    _fill(tmp_path)
    before = _tables(tmp_path)
    r = subprocess.run(
        [sys.executable, "-c", KILLER, str(tmp_path), str(kill_at)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert r.returncode in (0, -9), r.stderr
    assert _tables(tmp_path) == before  # a reader during the crashed state
    for f in tmp_path.rglob("*.parquet"):
        pq.read_table(f)
    with caplog.at_level(logging.INFO, logger="idr_eval.store"):
        store = RunStore(tmp_path)  # recovery
    assert _tables(tmp_path) == before
    left = [p for p in tmp_path.rglob("*") if p.name.startswith(".") and p.suffix == ".tmp"]
    assert not left
    step = kill_at % 8  # per cell: steps rename, episodes rename (the commit), 6 removals
    said = " ".join(caplog.messages)
    if r.returncode == -9 and step == 1:  # the steps file landed alone: removed
        assert "its episodes file never landed" in said
    elif r.returncode == -9 and step >= 2:  # the commit landed: what it merged is removed
        assert "merged into a compacted file" in said
    store.compact()
    assert _tables(tmp_path) == before
    assert len(list(tmp_path.rglob("*.parquet"))) == 4


def test_readers_project_columns(tmp_path) -> None:
    _fill(tmp_path)
    store = RunStore(tmp_path, read_only=True)
    t = store.episodes(columns=["cell_id", "success"])
    assert t.column_names == ["cell_id", "success"] and t.num_rows == 12
    assert len(store.stored_keys()) == 12


def test_a_cell_is_compacted_as_soon_as_its_last_episode_is_stored(tmp_path) -> None:
    """Cells run one after another: when the E cell's first batch lands, the baseline cell
    (all 6 episodes stored) is already one file per table; a resume changes nothing."""
    from pipeline.execution.runner import plan_run, run_episodes
    from pipeline.planning.config import load_config

    cfg = load_config(
        ROOT / "conf" / "smoke.yaml",
        ["executor.kind=inline", "executor.flush_every=1", "tracking.enabled=false"],
    )
    plan = plan_run(cfg, tmp_path / "run")
    seen: list[tuple[str, list[str]]] = []

    def files_of_baseline(batch) -> None:
        names = sorted(p.name for p in (tmp_path / "run" / "episodes").glob("cell=baseline/*"))
        seen.append((batch[0].episode.cell_id, names))

    run_episodes(plan, on_flush=files_of_baseline)
    first_e = next(names for cell, names in seen if cell == "E")
    assert len(first_e) == 1 and first_e[0].startswith("compact-")
    # while the baseline cell ran, its batches were kept as they landed (crash safety)
    assert max(len(names) for cell, names in seen if cell == "baseline") == 5
    store = RunStore(tmp_path / "run")
    assert len(store.stored_keys()) == 12
    steps = store.steps(columns=[*KEY, "inference_index"]).to_pandas()
    assert not steps.duplicated().any()
