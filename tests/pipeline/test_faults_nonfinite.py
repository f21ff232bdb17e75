"""Fault 2, non-finite numbers: a backbone that returns NaN or inf, and a simulation that
diverges (a real MuJoCo instability in the tabletop env, and a NaN state from the fake env).
The step is never sent to the simulator, the episode ends as a clear error row, and every
other episode is exactly what a clean run gives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline.execution.runner import plan_run, run_episodes
from pipeline.planning.config import config_from_dict, load_config
from pipeline.results.store import VOLATILE_COLUMNS, RunStore
from tests.support.fault_audit import assert_clean, audit

CONF = Path(__file__).resolve().parents[2] / "conf"
GUARANTEE = (
    "the step is not sent to the simulator; the episode ends as an error row naming the cause; "
    "every other episode is unaffected"
)


def _run(run_dir: Path, *overrides: str) -> tuple[pd.DataFrame, object]:
    cfg = load_config(
        CONF / "smoke.yaml",
        ["tracking.enabled=false", "executor.kind=inline", "executor.max_attempts=1", *overrides],
    )
    plan = plan_run(cfg, run_dir)
    run_episodes(plan)
    eps = RunStore(run_dir).episodes().to_pandas().drop(columns=list(VOLATILE_COLUMNS))
    return eps.set_index(["cell_id", "task_id", "episode_index"]).sort_index(), plan


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> pd.DataFrame:
    return _run(tmp_path_factory.mktemp("clean") / "run")[0]


@pytest.mark.parametrize("value", [".nan", ".inf", "-.inf"])
def test_fake_nonfinite_action_and_state(tmp_path, clean, fault_log, value) -> None:
    eps, plan = _run(
        tmp_path / "run",
        "backbone.kind=tests.doubles.backbones:FaultyMarkerBackbone",
        "env.suite=tests.doubles.envs:FaultyMarkerEnv",
        "backbone.params.nonfinite_calls=[0]",  # the first inference of the run
        f"backbone.params.nonfinite_value={value}",
        "env.params.nan_state_on=[1]",  # episode 1 of every cell and task diverges at step 2
    )
    outcome = audit(plan.run_dir, {s.key for s in plan.all_specs()})
    assert_clean(outcome)
    bad_action = eps.loc[("baseline", "reach", 0)]
    assert bad_action.error.startswith("NonFiniteActionError: non-finite action at step 0")
    assert "not sent to the env" in bad_action.error
    bad_state = eps.xs(1, level="episode_index")
    assert len(bad_state) == 4
    assert bad_state.error.str.startswith(
        "NonFiniteStateError: non-finite state after step 2"
    ).all()
    ok = eps[eps.error.isna()]
    assert len(ok) == 12 - 1 - 4
    # the rest: as in a clean run (dtypes differ where the faulty run has nulls), but for the
    # backbone's name (the faulty double's entry point)
    assert set(ok.backbone) == {"tests.doubles.backbones:FaultyMarkerBackbone"}
    pd.testing.assert_frame_equal(
        ok.drop(columns="backbone"),
        clean.loc[ok.index].drop(columns="backbone"),
        check_dtype=False,
    )
    fault_log.record(
        f"non-finite action ({value.replace('.', '')}) / NaN state (fake env)",
        f"fake backbone returns {value} at the first inference; fake env state NaN at step 2",
        GUARANTEE,
        {**outcome, "unaffected_episodes_identical_to_clean_run": len(ok)},
    )


@pytest.mark.sim
@pytest.mark.slow
def test_mujoco_instability_and_nan_action_on_the_tabletop(tmp_path, monkeypatch, fault_log):
    """A real MuJoCo divergence (qvel := NaN inside the physics, through the env's fault hook)
    is detected from MuJoCo's own warnings, although MuJoCo resets the state and goes on; a
    NaN action never reaches MuJoCo's step."""
    import torch

    from workers.episode import worker as episode_worker

    cfg = config_from_dict(
        {
            "name": "unstable",
            "backbone": {"kind": "noop", "params": {"chunk_len": 4}, "replan_steps": 4},
            "env": {
                "suite": "tests.doubles.tabletop:UnstableTabletopEnv",
                "tasks": ["pick_color"],
                "params": {
                    "cameras": ["agentview"],
                    "image_size": 32,
                    "max_steps": {"pick_color": 12},
                    "inject_instability": [0, 5],  # episode 0, before control step 6
                },
            },
            "episodes_per_task": 2,
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline", "max_attempts": 1},
            "tracking": {"enabled": False},
        }
    )
    plan = plan_run(cfg, tmp_path / "run")
    worker = episode_worker.EpisodeWorker(plan.worker_spec)  # one simulator for the whole test
    monkeypatch.setattr(episode_worker, "EpisodeWorker", lambda spec: worker)
    monkeypatch.setattr(worker, "close", lambda: None)
    run_episodes(plan)

    outcome = audit(plan.run_dir, {s.key for s in plan.all_specs()})
    assert_clean(outcome)
    store = RunStore(plan.run_dir)
    eps = store.episodes().to_pandas().set_index("episode_index")
    assert eps.loc[0, "error"].startswith("SimulationUnstableError: MuJoCo simulation unstable")
    assert "velocities (qvel)" in eps.loc[0, "error"]
    assert pd.isna(eps.loc[1, "error"]) and eps.loc[1, "steps"] == 12
    # episode 1 ran after the unstable one on the same simulator: identical to a rerun
    again = worker.run_episode(plan.specs[1])
    assert again.episode.error is None
    stored_steps = store.steps().to_pandas()
    assert [list(a) for a in stored_steps.action_final] == [s.action_final for s in again.steps]
    for col in ("success", "steps", "init_state_id", "instruction"):
        assert getattr(again.episode, col) == eps.loc[1, col]

    # a NaN action: refused before MuJoCo steps
    scene = worker.env._scene("pick_color")
    real_step, sent = scene.step, []
    monkeypatch.setattr(scene, "step", lambda a: sent.append(a) or real_step(a))
    monkeypatch.setattr(
        worker.backbone,
        "predict_chunk",
        lambda obs, noise=None, intervention=None: torch.full((obs.batch_size, 4, 7), np.nan),
    )
    nan_result = worker.run_episode(plan.specs[1])
    assert nan_result.episode.error.startswith("NonFiniteActionError")
    assert sent == [] and worker.env._clock.steps == 0  # nothing counted
    worker.env.close()
    fault_log.record(
        "MuJoCo instability / NaN action (tabletop, robosuite + MuJoCo 3)",
        "env fault hook sets qvel to NaN inside the physics at step 6; a backbone returning NaN",
        GUARANTEE + "; MuJoCo's silent reset is detected from its warning counters",
        {**outcome, "mujoco_steps_sent_with_nan_action": len(sent)},
    )


@pytest.mark.sim
@pytest.mark.slow
def test_a_diverging_libero_scene_is_an_error_row(tmp_path, monkeypatch, fault_log):
    """LIBERO is MuJoCo too: a divergence (qvel := NaN inside the physics) is detected from
    MuJoCo's warnings, the episode is one SimulationUnstableError row, and the next episode on
    the same simulator is what a rerun gives."""
    from workers.episode import worker as episode_worker

    cfg = config_from_dict(
        {
            "name": "unstable-libero",
            "backbone": {"kind": "noop", "params": {"action_dim": 7, "chunk_len": 4}},
            "env": {
                "suite": "tests.doubles.libero:UnstableLiberoEnv",
                "tasks": ["libero_spatial/0"],
                "params": {
                    "suites": ["libero_spatial"],
                    "max_steps": {"libero_spatial": 10},
                    "inject_instability": [0, 4],  # episode 0, before control step 5
                },
            },
            "episodes_per_task": 2,
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline", "max_attempts": 1},
            "tracking": {"enabled": False},
        }
    )
    plan = plan_run(cfg, tmp_path / "run")
    worker = episode_worker.EpisodeWorker(plan.worker_spec)  # one simulator for the whole test
    monkeypatch.setattr(episode_worker, "EpisodeWorker", lambda spec: worker)
    monkeypatch.setattr(worker, "close", lambda: None)
    try:
        run_episodes(plan)
        outcome = audit(plan.run_dir, {s.key for s in plan.all_specs()})
        assert_clean(outcome)
        eps = RunStore(plan.run_dir).episodes().to_pandas().set_index("episode_index")
        assert eps.loc[0, "error"].startswith("SimulationUnstableError: MuJoCo simulation unstable")
        assert "at step 5 of libero_spatial/0" in eps.loc[0, "error"]
        assert pd.isna(eps.loc[1, "error"]) and eps.loc[1, "steps"] == 10
        again = worker.run_episode(plan.specs[1])
        assert again.episode.error is None
        for col in ("success", "steps", "init_state_id"):
            assert getattr(again.episode, col) == eps.loc[1, col]
    finally:
        worker.env.close()
    fault_log.record(
        "MuJoCo instability (LIBERO, hf-libero + MuJoCo 3)",
        "env fault hook sets qvel to NaN inside LIBERO's physics at step 5 of episode 0",
        GUARANTEE + "; MuJoCo's silent reset is detected from its warning counters",
        outcome,
    )
