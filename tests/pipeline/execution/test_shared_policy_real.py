"""The shared policy service on a real lerobot policy (the tiny VLA): the same tables as in-actor
with the same forward rows. A file of its own: its two runs are the longest of the
shared-policy tests, and xdist places files whole."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config
from tests.pipeline.execution.test_runner import _episodes, _steps
from tests.pipeline.execution.test_shared_policy import CONF, SHARED

REAL = [  # the tiny VLA on two tabletop tasks, diagnose and E with tau calibrated: 8 episodes
    "tracking.enabled=false",
    "env.tasks=[pick_color,stack_color]",  # instructions of two lengths
    # 15 inferences an episode at most: enough arrivals to batch, a third of the tasks' budgets
    "env.params.max_steps={pick_color: 60, stack_color: 60}",
    "episodes_per_task=2",
    "grid=[{mode: [diagnose, E]}]",
]


def _real(tmp_path: Path, name: str, *overrides: str):
    cfg = load_config(CONF / "tiny_vla.yaml", [*REAL, *overrides])
    summary = execute(plan_run(cfg, tmp_path / name))
    assert summary.stored == 8 and summary.errors == 0
    # an actor that dies under a loaded machine's memory pressure has its episodes run again:
    # the retry count differs, the results must not
    return _episodes(tmp_path / name).drop(columns="attempt"), _steps(tmp_path / name)


@pytest.mark.slow
def test_a_real_network_gives_the_same_tables_shared_and_in_actor(tmp_path, ray_local):
    """The tiny VLA (a real lerobot policy; its actions move by ~1e-5 between forward shapes):
    shared, with 2 actors x 2 envs gathering arrivals for 20 ms into forwards of up to 4
    requests, gives one calibrated tau and the tables in-actor gives with the same forward rows,
    where each env's requests are forwarded alone. (That other arrivals in the shared service
    change no table is the fake-policy tests' property, in test_shared_policy.py.)"""
    if not (CONF.parent / "checkpoints" / "tiny_vla" / "config.json").exists():
        pytest.skip("checkpoints/tiny_vla not built (make setup builds it)")
    shared = [*SHARED, "executor.max_batch=4"]
    eps1, steps1 = _real(
        tmp_path, "a", *shared, "executor.envs_per_worker=2", "executor.batch_wait_ms=20"
    )
    assert set(eps1.numerics) == {"rows=12 threads=1"}
    assert eps1[eps1.cell_id == "E"].tau.nunique() == 1  # one calibrated tau per config
    eps2, steps2 = _real(tmp_path, "c", "executor.forward_rows=12")  # in-actor, same shape
    pd.testing.assert_frame_equal(eps1, eps2)
    pd.testing.assert_frame_equal(steps1, steps2)
