"""The scheduler's policy at unit level, on a scripted executor: dedup, retries, requeues,
error rows made from the spec alone, stages on one executor."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.execution.executors import Outcome
from pipeline.execution.runner import plan_run
from pipeline.execution.scheduler import Scheduler
from pipeline.execution.writer import BatchWriter
from pipeline.planning.config import load_config
from pipeline.results.store import RunStore
from tests.doubles.executors import ScriptedExecutor
from workers.episode.rows import SPEC_COLUMNS, EpisodeResult, EpisodeRow, EpisodeSpec

CONF = Path(__file__).resolve().parents[3] / "conf"


def _specs(tmp_path: Path, n: int = 4) -> list[EpisodeSpec]:
    cfg = load_config(CONF / "smoke.yaml", ["tracking.enabled=false", "executor.kind=inline"])
    return plan_run(cfg, tmp_path / "plan").specs[:n]


def _ok(spec: EpisodeSpec, success: bool = True) -> Outcome:
    return Outcome(spec, result=EpisodeResult(EpisodeRow.from_spec(spec, success=success), []))


def _scheduler(tmp_path: Path, script, max_attempts: int = 3) -> tuple[Scheduler, RunStore]:
    store = RunStore(tmp_path / "run")
    ex = ScriptedExecutor(script)
    return Scheduler(ex, BatchWriter(store, 2), max_attempts, total=0), store


def _stored(store: RunStore) -> list[dict]:
    return store.episodes().to_pylist()


def test_a_result_returned_twice_is_stored_once(tmp_path) -> None:
    specs = _specs(tmp_path)
    sched, store = _scheduler(tmp_path, lambda s: [_ok(s), _ok(s, success=False)])
    summary = sched.run_stage(specs)
    rows = _stored(store)
    assert len(rows) == len(specs) == summary.stored
    assert summary.duplicates_dropped == len(specs)
    assert all(r["success"] for r in rows)  # the first result won; the second was dropped


def test_error_rows_are_retried_until_the_last_attempt(tmp_path) -> None:
    specs = _specs(tmp_path, 2)

    def script(s: EpisodeSpec) -> list[Outcome]:
        if s.episode_index == 0 and s.attempt < 2:  # fails once, then succeeds
            return [Outcome(s, result=EpisodeResult(EpisodeRow.error_row(s, "boom"), []))]
        if s.episode_index == 1:  # always fails
            return [Outcome(s, result=EpisodeResult(EpisodeRow.error_row(s, "boom"), []))]
        return [_ok(s)]

    sched, store = _scheduler(tmp_path, script, max_attempts=3)
    summary = sched.run_stage(specs)
    by_index = {r["episode_index"]: r for r in _stored(store)}
    assert by_index[0]["error"] is None and by_index[0]["attempt"] == 2
    assert by_index[1]["error"] == "boom" and by_index[1]["attempt"] == 3
    assert summary.retries == 1 + 2 and summary.errors == 1


def test_requeued_episodes_are_not_charged_an_attempt(tmp_path) -> None:
    specs = _specs(tmp_path, 1)
    calls: list[int] = []

    def script(s: EpisodeSpec) -> list[Outcome]:
        calls.append(s.attempt)
        return [Outcome(s, requeue=True)] if len(calls) < 3 else [_ok(s)]

    sched, store = _scheduler(tmp_path, script, max_attempts=1)
    sched.run_stage(specs)
    assert calls == [1, 1, 1] and [r["attempt"] for r in _stored(store)] == [1]


def test_lost_at_the_last_attempt_stores_an_error_row_from_the_spec(tmp_path) -> None:
    """The error row of a dead actor agrees with the row the actor would have written on
    every column the spec fixes (suite of the task, task name, step budget, ...)."""
    (spec,) = _specs(tmp_path, 1)
    sched, store = _scheduler(tmp_path, lambda s: [Outcome(s, lost="actor died")], 2)
    summary = sched.run_stage([spec])
    (row,) = _stored(store)
    assert row["error"] == "actor died" and row["attempt"] == 2 and summary.errors == 1
    expected = EpisodeRow.from_spec(spec.retry())
    for col in SPEC_COLUMNS:
        assert row[col] == getattr(expected, col), col
    assert row["suite"] == "fake_marker" and row["task_name"] and row["max_steps"] > 0


def test_stages_share_the_executor_and_skip_stored_keys(tmp_path) -> None:
    specs = _specs(tmp_path, 4)
    sched, store = _scheduler(tmp_path, lambda s: [_ok(s)])
    sched.run_stage(specs[:2])
    sched.run_stage(specs)  # a later stage that repeats two stored keys
    assert len(_stored(store)) == 4 and sched.summary.skipped == 2
    assert [s.key for s in sched.executor.submitted] == [s.key for s in specs]


@pytest.mark.parametrize("slots", [1, 3])
def test_the_executor_is_never_overfilled(tmp_path, slots) -> None:
    specs = _specs(tmp_path, 4)
    sched, _ = _scheduler(tmp_path, lambda s: [_ok(s)])
    sched.executor.slots = slots  # ScriptedExecutor asserts on a submit past free_slots()
    assert sched.run_stage(specs).stored == 4


def test_an_actors_row_and_a_dead_actors_error_row_agree_on_spec_columns(tmp_path) -> None:
    """For an env whose tasks name suites of their own (as LIBERO's do), the error row the
    scheduler stores for a dead actor and the row the actor writes for the same spec agree on
    every column the spec fixes: the task's suite, not the config's env.suite."""
    from workers.episode.worker import EpisodeWorker

    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "tracking.enabled=false",
            "executor.kind=inline",
            "env.suite=tests.doubles.envs:TwoSuiteMarkerEnv",
            "env.tasks=[reach_chain]",
        ],
    )
    plan = plan_run(cfg, tmp_path / "plan")
    spec = plan.specs[0]
    worker = EpisodeWorker(plan.worker_spec)
    try:
        actor_row = worker.run_episode(spec).episode
    finally:
        worker.close()
    assert actor_row.error is None and actor_row.suite == "marker_b"
    sched, store = _scheduler(tmp_path, lambda s: [Outcome(s, lost="actor died")], 1)
    sched.run_stage([spec])
    (error_row,) = _stored(store)
    assert error_row["error"] == "actor died"
    assert {c: error_row[c] for c in SPEC_COLUMNS} == {
        c: getattr(actor_row, c) for c in SPEC_COLUMNS
    }
