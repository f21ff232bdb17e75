"""Fault 5, an actor out of memory: an allocation past an RLIMIT_AS set for the test fails
(MemoryError), or the process is then SIGKILLed as the kernel's OOM killer would; the
actor is replaced, the episode retried, and the run completes."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.execution.runner import plan_run, run_episodes
from pipeline.planning.config import load_config
from pipeline.results.store import RunStore
from tests.support.fault_audit import assert_clean, audit

CONF = Path(__file__).resolve().parents[2] / "conf"
GUARANTEE = "the actor is replaced, the episode retried on a fresh one; the run completes"


def _run(tmp_path: Path, *overrides: str):
    cfg = load_config(
        CONF / "smoke.yaml", ["tracking.enabled=false", "env.tasks=[reach]", *overrides]
    )
    plan = plan_run(cfg, tmp_path / "run")
    summary = run_episodes(plan)
    eps = RunStore(plan.run_dir).episodes().to_pandas()
    return plan, summary, eps


_ALLOCATE_PAST_THE_LIMIT = """
import resource
from tests.doubles.faults import exhaust_memory

before = resource.getrlimit(resource.RLIMIT_AS)
try:
    exhaust_memory(32)
except MemoryError as e:
    assert "past RLIMIT_AS" in str(e), e
else:
    raise AssertionError("no MemoryError")
assert resource.getrlimit(resource.RLIMIT_AS) == before
bytearray(64 * 2**20)  # the process is usable again
"""


def test_allocation_past_the_limit_fails_and_the_limit_is_restored() -> None:
    """In a fresh interpreter: what earlier tests left mapped in a shared worker process (a
    library's allocator holding freed pages) must not decide whether the limit bites."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    done = subprocess.run(
        [sys.executable, "-c", _ALLOCATE_PAST_THE_LIMIT],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-2000:]


def test_inline_out_of_memory_replaces_the_worker(tmp_path, fault_log) -> None:
    plan, summary, eps = _run(
        tmp_path,
        "executor.kind=inline",
        "env.suite=tests.doubles.envs:FaultyMarkerEnv",
        f"env.params={{oom_on: [0], once_dir: {tmp_path / 'once'}}}",
    )
    outcome = audit(plan.run_dir, {s.key for s in plan.all_specs()})
    assert_clean(outcome)
    assert eps.error.isna().all() and summary.retries == 1 and summary.actors_replaced == 1
    fault_log.record(
        "actor out of memory (inline)",
        "fake env reset allocates past RLIMIT_AS = its size + 64 MB (MemoryError), once",
        GUARANTEE,
        {**outcome, "workers_replaced": summary.actors_replaced, "retries": summary.retries},
    )


@pytest.mark.slow
def test_ray_actor_out_of_memory_is_replaced(tmp_path, ray_local, fault_log) -> None:
    plan, summary, eps = _run(
        tmp_path,
        "executor.kind=ray",
        "executor.max_attempts=2",
        "env.suite=tests.doubles.envs:FaultyMarkerEnv",
        f"env.params={{oom_on: [0], oom_kill_on: [1], once_dir: {tmp_path / 'once'}}}",
    )
    outcome = audit(plan.run_dir, {s.key for s in plan.all_specs()})
    assert_clean(outcome)
    assert eps.error.isna().all()  # both episodes re-ran on fresh actors
    assert sorted(eps.attempt) == [1, 1, 1, 1, 2, 2]
    assert summary.actors_replaced == 2 and summary.retries == 2
    fault_log.record(
        "actor out of memory (ray)",
        "fake env reset allocates past RLIMIT_AS = its size + 64 MB: MemoryError in one actor, "
        "SIGKILL (as the OOM killer) in another, once each",
        GUARANTEE,
        {**outcome, "actors_replaced": summary.actors_replaced, "retries": summary.retries},
    )
