"""Faults: dead actors are replaced, failing episodes retried, nothing lost or stored twice."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipeline.execution.executors.ray_pool import RayActorPool
from pipeline.execution.runner import plan_run, run_episodes
from pipeline.planning.config import load_config
from pipeline.results.store import RunStore
from tests.support.fault_audit import assert_clean, audit

ROOT = Path(__file__).resolve().parents[3]
CONF = ROOT / "conf"


def _plan(tmp_path: Path, *overrides: str):
    cfg = load_config(CONF / "smoke.yaml", ["tracking.enabled=false", *overrides])
    return plan_run(cfg, tmp_path / "run")


def _keys(run_dir: Path) -> Counter:
    t = RunStore(run_dir).episodes().to_pydict()
    return Counter(zip(t["cell_id"], t["task_id"], t["episode_index"], strict=True))


def test_episode_exception_becomes_error_row_and_is_retried(tmp_path) -> None:
    plan = _plan(
        tmp_path,
        "executor.kind=inline",
        "env.suite=tests.doubles.envs:FaultyMarkerEnv",
        "env.params={fail_once: [1], fail_always: [2]}",
        "executor.max_attempts=3",
    )
    summary = run_episodes(plan)
    eps = RunStore(plan.run_dir).episodes().to_pandas()
    assert len(eps) == 12 and set(_keys(plan.run_dir).values()) == {1}
    failed_always = eps[eps.episode_index == 2]
    assert failed_always.error.str.contains("injected failure").all()
    assert (failed_always.attempt == 3).all() and not failed_always.success.any()
    # fail_once: one failure per (process, episode 1) -> retried once, then fine
    once = eps[eps.episode_index == 1]
    assert once.error.isna().sum() >= 3 and (once.attempt <= 2).all()
    assert summary.errors == 4  # 2 cells x 2 tasks for episode 2
    assert summary.retries == 4 * 2 + 1


@pytest.mark.slow
def test_ray_kill_mid_run_loses_and_duplicates_nothing(tmp_path, ray_local, fault_log) -> None:
    plan = _plan(
        tmp_path, "executor.kind=ray", "backbone.params.delay_s=0.01", "executor.flush_every=1"
    )
    pool = RayActorPool(plan.worker_spec, plan.cfg.executor)
    stored = RunStore(plan.run_dir, read_only=True).stored_count
    killed: list[int] = []

    def killer() -> None:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline and stored() < 2:
            time.sleep(0.05)
        if stored() < 2:
            return  # the run never got going: the assertion below says so
        aid, actor = next(iter(pool.actors.items()))
        ray_local.kill(actor, no_restart=True)
        killed.append(aid)

    t = threading.Thread(target=killer, daemon=True)
    t.start()
    summary = run_episodes(plan, executor=pool)
    t.join(5)
    assert killed and summary.actors_replaced >= 1
    keys = _keys(plan.run_dir)
    assert len(keys) == 12 and set(keys.values()) == {1}
    assert summary.errors == 0  # the episodes of the dead actor were re-run, not failed
    outcome = audit(plan.run_dir, {s.key for s in plan.specs})
    assert_clean(outcome)
    fault_log.record(
        "actor killed (ray.kill)",
        "ray.kill of a busy actor after 2 episodes are stored",
        "replaced, its episode re-run; nothing lost or stored twice",
        {**outcome, "actors_replaced": summary.actors_replaced},
    )


@pytest.mark.slow
def test_crashing_process_is_retried_then_recorded(tmp_path, ray_local, fault_log) -> None:
    plan = _plan(
        tmp_path,
        "executor.kind=ray",
        "env.suite=tests.doubles.envs:FaultyMarkerEnv",
        "env.params={exit_on: [0]}",
        "env.tasks=[reach]",
        "executor.max_attempts=2",
    )
    summary = run_episodes(plan)
    eps = RunStore(plan.run_dir).episodes().to_pandas()
    assert len(eps) == 6 and set(_keys(plan.run_dir).values()) == {1}
    dead = eps[eps.episode_index == 0]
    assert len(dead) == 2 and dead.error.str.contains("actor died").all()
    assert eps[eps.episode_index != 0].error.isna().all()
    assert summary.actors_replaced >= 2
    outcome = audit(plan.run_dir, {s.key for s in plan.specs})
    assert_clean(outcome)
    fault_log.record(
        "actor process crashes (segfault-like exit)",
        "fake env calls os._exit(17) in every reset of episode 0",
        "replaced and retried up to max_attempts, then one error row per key; the rest unaffected",
        {**outcome, "actors_replaced": summary.actors_replaced},
    )


def test_driver_killed_mid_run_then_resumed(tmp_path, fault_log) -> None:
    out = tmp_path / "run"
    args = [
        sys.executable,
        "-m",
        "pipeline.cli",
        "run",
        "conf/smoke.yaml",
        "--out",
        str(out),
        "executor.kind=inline",
        "tracking.enabled=false",
        "executor.flush_every=1",
        "backbone.params.delay_s=0.02",
    ]
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and len(list((out / "episodes").rglob("*.parquet"))) < 3:
        time.sleep(0.05)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    partial = _keys(out)
    assert 3 <= len(partial) < 12, "the kill should land mid-run"
    for f in out.rglob("*.parquet"):
        pq.read_table(f)  # every file readable
    r = subprocess.run(args, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    keys = _keys(out)
    assert len(keys) == 12 and set(keys.values()) == {1}
    assert f"{len(partial)} already stored" in r.stdout
    cells, tasks = ("baseline", "E"), ("reach", "reach_chain")
    outcome = audit(out, {(c, t, i) for c in cells for t in tasks for i in range(3)})
    assert_clean(outcome)
    fault_log.record(
        "driver killed by SIGKILL",
        "SIGKILL to `idr-eval run` after 3 batches; then the same command",
        "no unreadable file; the same command resumes, nothing lost or stored twice",
        {**outcome, "stored_at_kill": len(partial)},
    )
