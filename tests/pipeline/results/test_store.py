"""The Parquet store: fixed schemas, atomic batches, crash recovery, keys stored once."""

from __future__ import annotations

import pyarrow.parquet as pq
import pytest

from pipeline.results.store import EPISODE_SCHEMA, STEP_SCHEMA, RunStore
from tests.doubles import rows
from workers.episode.rows import EpisodeResult, EpisodeRow


def _result(
    cell: str, task: str, i: int, n_steps: int = 2, error: str | None = None
) -> EpisodeResult:
    ep = {
        "run_id": "r",
        "cell_id": cell,
        "task_id": task,
        "episode_index": i,
        "success": i % 2 == 0,
        "steps": 10,
        "error": error,
        "suite": "s",
    }
    steps = [
        {
            "run_id": "r",
            "cell_id": cell,
            "task_id": task,
            "episode_index": i,
            "inference_index": k,
            "step": 4 * k,
            "e_img": 1.5,
            "action_base": [0.1, 0.2],
            "action_final": [0.1, 0.25],
        }
        for k in range(n_steps)
    ]
    return rows.result(ep, steps)


def test_roundtrip_with_fixed_schemas(tmp_path) -> None:
    store = RunStore(tmp_path)
    assert store.write([_result("E", "t", 0), _result("baseline", "t", 0, 3)]) == 2
    eps, steps = store.episodes(), store.steps()
    assert eps.schema == EPISODE_SCHEMA and steps.schema == STEP_SCHEMA
    assert eps.num_rows == 2 and steps.num_rows == 5
    assert store.stored_keys() == {("E", "t", 0), ("baseline", "t", 0)}
    assert steps.column("action_final").to_pylist()[0] == pytest.approx([0.1, 0.25])
    # partitioned by cell; every file is a complete Parquet file
    files = sorted(p.relative_to(tmp_path).parts[:2] for p in tmp_path.rglob("*.parquet"))
    assert ("episodes", "cell=E") in files and ("steps", "cell=baseline") in files
    for f in tmp_path.rglob("*.parquet"):
        pq.read_metadata(f)


def test_unknown_column_is_refused() -> None:
    """A misspelt column cannot reach the store: rows are typed, with slots."""
    with pytest.raises(TypeError, match="sucess"):
        rows.episode_row(sucess=True)
    r = _result("E", "t", 0)
    with pytest.raises(AttributeError, match="sucess"):
        r.episode.sucess = True  # type: ignore[attr-defined]


def test_schemas_are_derived_from_the_row_types() -> None:
    """One owner of the format: every field of EpisodeRow / StepRow is a column, in order,
    with the Arrow type its hint names (F32 -> float32, X | None -> nullable X)."""
    from dataclasses import fields

    from workers.episode.rows import StepRow

    assert EPISODE_SCHEMA.names == [f.name for f in fields(EpisodeRow)]
    assert STEP_SCHEMA.names == [f.name for f in fields(StepRow)]
    assert str(EPISODE_SCHEMA.field("alpha").type) == "double"
    assert str(EPISODE_SCHEMA.field("crn").type) == "bool"
    assert str(STEP_SCHEMA.field("e_img").type) == "float"
    assert str(STEP_SCHEMA.field("action_base").type) == "list<item: float>"


def test_recovery_removes_orphans_and_temp_files(tmp_path) -> None:
    store = RunStore(tmp_path)
    store.write([_result("E", "t", 0)])
    # a crash between the steps rename and the episodes rename leaves an orphan steps batch
    (orphan,) = (tmp_path / "steps").rglob("*.parquet")
    orphan.rename(orphan.with_name("batch-000099-deadbeef.parquet"))
    (tmp_path / "steps" / "cell=E" / "batch-000001-aaaa.parquet").write_bytes(
        b""
    )  # never renamed in
    (tmp_path / "episodes" / "cell=E" / ".batch-000100-x.parquet.tmp").write_bytes(b"PAR1 half")
    reopened = RunStore(tmp_path)
    assert reopened.steps().num_rows == 0  # orphan steps removed: their episode was never stored
    assert not list(tmp_path.rglob("*.tmp"))
    assert reopened.stored_keys() == {("E", "t", 0)}
    # the next batch number continues after the existing ones
    reopened.write([_result("E", "t", 1)])
    assert len(list((tmp_path / "episodes" / "cell=E").glob("batch-000002-*.parquet"))) == 1


def test_read_only_reader_of_a_live_run_leaves_in_flight_batches_alone(tmp_path) -> None:
    """report/compare/figures may open a run its driver is writing: a steps batch whose
    episodes batch is not renamed in yet must be neither deleted nor counted."""
    store = RunStore(tmp_path)
    store.write([_result("E", "t", 0)])
    (done,) = (tmp_path / "steps").rglob("*.parquet")
    in_flight = done.with_name("batch-000002-cafe.parquet")
    in_flight.write_bytes(done.read_bytes())  # steps landed, episodes about to
    reader = RunStore(tmp_path, read_only=True)
    assert in_flight.is_file()
    assert reader.steps().num_rows == 2 and reader.episodes().num_rows == 1
    with pytest.raises(RuntimeError, match="read-only"):
        reader.write([_result("E", "t", 1)])
    assert RunStore(tmp_path / "absent", read_only=True).episodes().num_rows == 0
    assert not (tmp_path / "absent").exists()


def test_batches_written_before_a_column_was_added_read_as_nulls(tmp_path) -> None:
    """A run dir from before the failure columns existed still reads, and resumes next to
    new batches: the missing columns come back null."""
    store = RunStore(tmp_path)
    store.write([_result("E", "t", 0)])
    (old,) = (tmp_path / "episodes").rglob("batch-*.parquet")
    table = pq.read_table(old)
    pq.write_table(table.drop_columns(["failure", "failure_detail"]), old)
    r = _result("E", "t", 1)
    r.episode.failure, r.episode.failure_detail = "timeout", "no success within 10 steps"
    RunStore(tmp_path).write([r])
    eps = RunStore(tmp_path).episodes()
    assert eps.schema == EPISODE_SCHEMA
    rows = eps.select(["episode_index", "failure"]).to_pylist()
    by_index = {r["episode_index"]: r["failure"] for r in rows}
    assert by_index == {0: None, 1: "timeout"}
