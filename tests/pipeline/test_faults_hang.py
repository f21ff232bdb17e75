"""Fault 1, hung episodes: cut off at executor.episode_timeout_s, worker replaced, retried or
recorded as a timeout error row; the run finishes."""

from __future__ import annotations

import signal
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import pytest

from pipeline.execution.runner import plan_run, run_episodes
from pipeline.execution.timeouts import EpisodeTimeout, alarm
from pipeline.planning.config import load_config
from pipeline.results.store import RunStore
from tests.doubles.backbones import FaultyMarkerBackbone
from tests.support.fault_audit import assert_clean, audit

CONF = Path(__file__).resolve().parents[2] / "conf"
GUARANTEE = (
    "cut off after executor.episode_timeout_s, its worker replaced; retried, or stored as a "
    "timeout error row after max_attempts; the run finishes"
)


def _run(tmp_path: Path, *overrides: str):
    cfg = load_config(CONF / "smoke.yaml", ["tracking.enabled=false", *overrides])
    plan = plan_run(cfg, tmp_path / "run")
    t0 = time.monotonic()
    summary = run_episodes(plan)
    return plan, summary, time.monotonic() - t0


def test_alarm_interrupts_a_hung_backbone_call() -> None:
    backbone = FaultyMarkerBackbone(hang_from_call=0)
    t0 = time.monotonic()
    with pytest.raises(EpisodeTimeout), alarm(0.3):
        backbone.predict_chunk(SimpleNamespace(batch_size=1))  # never returns
    assert time.monotonic() - t0 < 5


def test_alarm_reaches_the_main_thread_when_another_thread_could_take_the_signal() -> None:
    """A thread that does not block SIGALRM (a library's worker thread) while the main thread
    blocks it: a process-wide timer's signal goes to that thread and the main thread's hung
    call is never interrupted. The alarm must still cut the call off in the main thread."""
    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)
    other.start()  # started before the mask below, so it keeps SIGALRM unblocked
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGALRM})
    try:
        t0 = time.monotonic()
        with pytest.raises(EpisodeTimeout), alarm(0.3):
            time.sleep(20)  # a hung call; 20 s, not forever, so a regression fails, not hangs
        assert time.monotonic() - t0 < 5
        # the main thread's mask is as the caller left it
        assert signal.SIGALRM in signal.pthread_sigmask(signal.SIG_BLOCK, set())
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)
        stop.set()
        other.join()


@pytest.mark.parametrize(
    ("where", "overrides", "timeouts"),
    [
        # the env's reset of episode 2 never returns, in every attempt: 2 keys x 2 attempts
        (
            "env",
            [
                "env.tasks=[reach]",
                "env.suite=tests.doubles.envs:FaultyMarkerEnv",
                "env.params.hang_on=[2]",
            ],
            4,
        ),
        # the backbone's first call never returns: the one episode of the run
        (
            "backbone",
            [
                "env.tasks=[reach]",
                "episodes_per_task=1",
                "grid=[{mode: [baseline]}]",
                "backbone.kind=tests.doubles.backbones:FaultyMarkerBackbone",
                "backbone.params.hang_from_call=0",
            ],
            2,
        ),
    ],
)
def test_inline_hang_is_cut_off_and_recorded(tmp_path, fault_log, where, overrides, timeouts):
    plan, summary, wall = _run(
        tmp_path,
        "executor.kind=inline",
        "executor.episode_timeout_s=1",
        "executor.max_attempts=2",
        *overrides,
    )
    outcome = audit(plan.run_dir, {s.key for s in plan.all_specs()})
    assert_clean(outcome)
    eps = RunStore(plan.run_dir).episodes().to_pandas()
    hung = eps[eps.error.notna()]
    assert len(hung) == timeouts // 2 and (hung.attempt == 2).all()
    assert hung.error.str.contains("executor.episode_timeout_s=1").all()
    assert eps[eps.error.isna()].success.notna().all()
    assert summary.timeouts == timeouts and summary.actors_replaced == timeouts
    assert wall < 60
    fault_log.record(
        f"hung episode ({where}, inline)",
        f"fake {where} call that never returns; episode_timeout_s=1, SIGALRM",
        GUARANTEE,
        {**outcome, "timeouts": summary.timeouts, "workers_replaced": summary.actors_replaced},
    )


@pytest.mark.slow
def test_ray_hang_is_cut_off_and_retried(tmp_path, ray_local, fault_log) -> None:
    plan, summary, wall = _run(
        tmp_path,
        "executor.kind=ray",
        "executor.episode_timeout_s=4",
        "executor.max_attempts=2",
        "env.tasks=[reach]",
        "env.suite=tests.doubles.envs:FaultyMarkerEnv",
        f"env.params={{hang_on: [1], once_dir: {tmp_path / 'once'}}}",
    )
    outcome = audit(plan.run_dir, {s.key for s in plan.all_specs()})
    assert_clean(outcome)
    eps = RunStore(plan.run_dir).episodes().to_pandas()
    assert eps.error.isna().all()  # the hung episode was re-run on a fresh actor
    assert sorted(eps.attempt) == [1, 1, 1, 1, 1, 2]
    assert summary.timeouts == 1 and summary.actors_replaced == 1
    assert wall < 120
    fault_log.record(
        "hung episode (env, ray)",
        "fake env reset that never returns (once); episode_timeout_s=4",
        GUARANTEE,
        {**outcome, "timeouts": summary.timeouts, "actors_replaced": summary.actors_replaced},
    )
