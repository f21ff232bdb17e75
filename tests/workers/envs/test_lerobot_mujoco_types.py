"""lerobot's MuJoCo env types through ``env.suite: lerobot``: MetaWorld (its task names and
difficulty groups, the env's own 500-step budget, the instruction from the env) and ALOHA (a
480x640 camera the pre-flight matches on height and width, an episode run with a checkpoint
of that size)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, config_from_dict, load_config
from pipeline.results.store import RunStore
from training.toy_checkpoints import build_act
from workers.envs.checks import check_env
from workers.envs.factory import make_env

CONF = Path(__file__).resolve().parents[3] / "conf"
needs_metaworld = pytest.mark.skipif(
    importlib.util.find_spec("metaworld") is None,
    reason="metaworld is not installed (make setup installs it)",
)
needs_aloha = pytest.mark.skipif(
    importlib.util.find_spec("gym_aloha") is None,
    reason="gym-aloha is not installed (make setup installs it)",
)
pytestmark = [pytest.mark.sim]


@pytest.fixture(autouse=True)
def _rendering() -> None:
    from workers.rendering import configure_rendering

    configure_rendering()


def _cfg(backbone: dict, params: dict, **over) -> object:
    return config_from_dict(
        {
            "name": "lerobot_types",
            "backbone": backbone,
            "env": {"suite": "lerobot", "params": params},
            "episodes_per_task": 1,
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
            **over,
        }
    )


@needs_metaworld
def test_metaworld_tasks_are_named_and_keep_the_envs_budget_and_instruction() -> None:
    from lerobot.envs.metaworld import DIFFICULTY_TO_TASKS, TASK_DESCRIPTIONS

    env = make_env("lerobot", {"type": "metaworld", "task": "easy"})
    try:
        ids = [t.task_id for t in env.tasks()]
        assert ids == [f"easy/{name}" for name in DIFFICULTY_TO_TASKS["easy"]]
        # lerobot-eval's rollout gives an episode the env's _max_episode_steps, not the
        # config's episode_length (400)
        assert {t.max_steps for t in env.tasks()} == {500}
        check_env(env)
        name = DIFFICULTY_TO_TASKS["easy"][3]
        obs = env.reset(f"easy/{name}", 0, seed=0)
        assert obs.status.instruction == TASK_DESCRIPTIONS[name]
        assert obs.images["image"].shape == (480, 480, 3) and obs.state.shape == (4,)
        first = obs.images["image"].copy()
        again = env.reset(f"easy/{name}", 1, seed=0)  # seed 1: the objects move
        assert not np.array_equal(first, again.images["image"])
    finally:
        env.close()
    one = make_env("lerobot", {"type": "metaworld", "task": "assembly-v3", "max_steps": 20})
    try:
        assert [(t.task_id, t.max_steps) for t in one.tasks()] == [("assembly-v3", 20)]
    finally:
        one.close()


@needs_aloha
def test_aloha_is_matched_on_height_and_width_and_runs_a_checkpoint_of_its_size(tmp_path):
    params = {"type": "aloha", "task": "AlohaInsertion-v0", "max_steps": 6}
    square = build_act(tmp_path / "square", image=480, state=14, action=14, cams=("top",))
    with pytest.raises(ConfigError, match=r"'top' at 480x640 px.*\(3, 480, 480\)"):
        plan_run(_cfg({"kind": "lerobot", "params": {"path": str(square)}}, params), tmp_path / "a")
    assert not (tmp_path / "a").exists()
    ckpt = build_act(
        tmp_path / "act", image=(480, 640), state=14, action=14, cams=("top",), chunk=4
    )
    plan = plan_run(
        _cfg({"kind": "lerobot", "params": {"path": str(ckpt)}}, params), tmp_path / "r"
    )
    summary = execute(plan)
    assert summary.stored == 1 and summary.errors == 0
    (row,) = RunStore(tmp_path / "r").episodes().to_pylist()
    assert row["steps"] == 6 and row["task_id"] == "aloha" and row["error"] is None


@needs_metaworld
@pytest.mark.slow
def test_the_metaworld_preset_runs(tmp_path) -> None:
    cfg = load_config(
        CONF / "metaworld_smoke.yaml",
        ["executor.kind=inline", "tracking.enabled=false", "env.params.max_steps=10"],
    )
    summary = execute(plan_run(cfg, tmp_path / "run"))
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    assert summary.errors == 0 and len(eps) == summary.stored > 0
    assert (eps.steps == 10).all() and set(eps.perturbation) == {"none", "image_noise"}
    assert eps.instruction.str.len().min() > 10  # the env's task description, not a fixed one


@needs_metaworld
@pytest.mark.slow
def test_a_diverged_metaworld_episode_is_an_error_row_and_the_next_is_unaffected(tmp_path):
    """MuJoCo resets a diverged simulation and carries on: the suite reads MuJoCo's own
    warnings after every step, so the episode ends as an error row, and the next episode on
    the same env runs as in a clean run."""
    from workers.envs.suites.lerobot_envs.env import mujoco_data
    from workers.episode.worker import EpisodeWorker

    params = {"type": "metaworld", "task": "assembly-v3", "max_steps": 8}
    cfg = _cfg({"kind": "noop", "params": {"action_dim": 4, "chunk_len": 4}}, params)
    plan = plan_run(cfg.model_copy(update={"episodes_per_task": 2}), tmp_path / "run")
    worker = EpisodeWorker(plan.worker_spec)
    try:
        clean = worker.run_episode(plan.specs[1]).episode
        env = worker.env
        step = env.step

        def diverging(action):
            if env._clock.steps == 3:  # NaN velocities inside the physics, as a blow-up leaves them
                mujoco_data(env._env).qvel[:] = np.nan
            return step(action)

        env.step = diverging
        bad = worker.run_episode(plan.specs[0]).episode
        env.step = step
        again = worker.run_episode(plan.specs[1]).episode
    finally:
        worker.close()
    assert bad.error.startswith("SimulationUnstableError: MuJoCo simulation unstable at step 4")
    assert "velocities (qvel)" in bad.error or "accelerations (qacc)" in bad.error
    assert clean.error is None and again.error is None and again.steps == clean.steps == 8
    assert again.success == clean.success


@needs_aloha
def test_a_process_that_closed_an_aloha_env_exits(tmp_path) -> None:
    """dm_control frees ALOHA's rendering contexts when its physics is collected. An env kept
    alive by a reference cycle is collected at exit, and under pytest that waited forever on a
    render thread already gone: the process never exited. close() frees them. A child pytest
    runs such a test, and must exit (without the free: killed at the timeout)."""
    import subprocess
    import sys
    import textwrap

    (tmp_path / "test_child.py").write_text(
        textwrap.dedent(
            """
            import numpy as np

            def test_closed():
                from workers.rendering import configure_rendering
                configure_rendering()
                from workers.envs.factory import make_env
                env = make_env("lerobot", {"type": "aloha", "max_steps": 3})
                env.reset("aloha", 0, 0)
                env.step(np.zeros(14, dtype=np.float32))
                env.keep = env  # a cycle: collected only at exit
                env.close()
            """
        )
    )
    root = Path(__file__).resolve().parents[3]
    cmd = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--rootdir", str(root)]
    try:
        done = subprocess.run(
            [*cmd, str(tmp_path / "test_child.py")],
            cwd=root,
            capture_output=True,
            text=True,
            timeout=90,
        )
    except subprocess.TimeoutExpired:
        pytest.fail("the child pytest did not exit within 90 s of closing its ALOHA env")
    assert done.returncode == 0 and "1 passed" in done.stdout, done.stdout[-2000:]
