"""The ``gymnasium`` and ``lerobot`` suites on a real Gymnasium env (gym-pusht's PushT): the env
contract, the observation mapping, lerobot's seeding rule, the protocol record, the pre-flight
against a checkpoint, a run of the preset, and one clear error per bad input before any work."""

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

pytest.importorskip("gym_pusht", reason="gym-pusht is not installed (make setup installs it)")

CONF = Path(__file__).resolve().parents[3] / "conf"
PIXELS = {"obs_type": "pixels_agent_pos", "observation_width": 64, "observation_height": 64}
GYM = {"id": "gym_pusht/PushT-v0", "kwargs": PIXELS, "instruction": "push the T"}
LEROBOT = {"type": "pusht"}  # gym-pusht renders its observation at 96 px


def test_a_gymnasium_id_is_a_suite_that_keeps_the_env_contract() -> None:
    env = make_env("gymnasium", GYM)
    try:
        check_env(env)
        assert env.cameras == ("pixels",) and env.state_dim == 2 and env.action_dim == 2
        (task,) = env.tasks()
        assert task.max_steps == 300 and task.instruction == "push the T"  # the spec's limit
        obs = env.reset(task.task_id, 0, seed=3)
        assert obs.images["pixels"].shape == (64, 64, 3) and obs.images["pixels"].dtype == np.uint8
        assert obs.state.dtype == np.float32 and obs.status.instruction == "push the T"
    finally:
        env.close()


def test_the_lerobot_suite_builds_lerobots_env_and_seeds_episodes_as_lerobot_eval() -> None:
    import gym_pusht  # noqa: F401
    import gymnasium as gym

    env = make_env("lerobot", LEROBOT)
    try:
        check_env(env)
        assert env.cameras == ("image",)  # lerobot's observation.image
        (task,) = env.tasks()
        assert (task.task_id, task.suite, task.max_steps) == ("pusht", "pusht", 300)
        ours = env.reset("pusht", 2, seed=5)  # episode 2 of a run with seed 5: seed 7
        ref = gym.make("gym_pusht/PushT-v0", obs_type="pixels_agent_pos")
        theirs, _ = ref.reset(seed=7)
        assert np.array_equal(ours.images["image"], theirs["pixels"])
        assert np.array_equal(ours.state, theirs["agent_pos"].astype(np.float32))
        io = type(env).describe(**LEROBOT)
        assert io.replan == "chunk" and io.protocol["name"] == "lerobot"
    finally:
        env.close()


@pytest.mark.parametrize(
    ("suite", "params", "pattern"),
    [
        (
            "gymnasium",
            {"id": "gym_pusht/PushT-v7"},
            r"not a registered.*did you mean gym_pusht/PushT-v0",
        ),
        ("gymnasium", {**GYM, "images": {"top": "pixels/top"}}, r"images: \['pixels/top'\] not in"),
        ("gymnasium", {**GYM, "state": ["joints"]}, r"state: \['joints'\] not in"),
        ("gymnasium", {"id": "gym_pusht/PushT-v0"}, "observation is not a dict"),
        ("gymnasium", {"id": "nopkg_zz/Env-v0"}, "install the package that registers 'nopkg_zz'"),
        (
            "lerobot",
            {"type": "pushtt"},
            r"type='pushtt' is not a lerobot env type.*did you mean pusht",
        ),
        ("lerobot", {"type": "robocasa"}, r"type='robocasa': 'robocasa' is not installed"),
        # VLABench is imported at the first reset: the pre-flight's reset finds it missing
        ("lerobot", {"type": "vlabench"}, r"type='vlabench': 'VLABench' is not installed"),
        ("lerobot", {"type": "libero"}, r"robot_state.*use env.suite=libero"),
        ("lerobot", {**LEROBOT, "colour": 1}, "unexpected keyword argument 'colour'"),
        ("lerobot", {**LEROBOT, "episode_lenght": 9}, "did you mean 'episode_length'"),
    ],
)
def test_bad_env_params_are_refused_before_any_work(tmp_path, suite, params, pattern) -> None:
    module = {"robocasa": "robocasa", "vlabench": "VLABench"}.get(params.get("type", ""))
    if module is not None and importlib.util.find_spec(module) is not None:
        pytest.skip(f"{module} is installed here: nothing to refuse")
    cfg = config_from_dict(
        {
            "name": "bad",
            "backbone": {"kind": "noop", "params": {"action_dim": 2}},
            "env": {"suite": suite, "params": params},
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
        }
    )
    with pytest.raises(ConfigError, match=pattern):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_a_checkpoint_that_does_not_fit_the_env_is_refused_naming_both(tmp_path) -> None:
    ckpt = build_act(tmp_path / "act", image=64, state=2, action=2, cams=("image!",))
    cfg = config_from_dict(
        {
            "name": "misfit",
            "backbone": {"kind": "lerobot", "params": {"path": str(ckpt)}},
            "env": {"suite": "lerobot", "params": LEROBOT},  # 96 px, the checkpoint 64
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
        }
    )
    with pytest.raises(ConfigError, match=r"96.*64|64.*96"):
        plan_run(cfg, tmp_path / "run")
    wrong_task = cfg.model_copy(update={"env": cfg.env.model_copy(update={"tasks": ["pushy"]})})
    with pytest.raises(ConfigError, match="pushy"):
        plan_run(wrong_task, tmp_path / "run2")
    scene = cfg.model_copy(
        update={"env": cfg.env.model_copy(update={"tasks": ["pusht@camera_shift:0.1"]})}
    )
    with pytest.raises(ConfigError, match=r"cannot apply \['camera_shift'\].*image_noise"):
        plan_run(scene, tmp_path / "run3")


@pytest.mark.slow
def test_the_pusht_preset_runs_with_image_perturbations(tmp_path) -> None:
    cfg = load_config(
        CONF / "pusht_smoke.yaml",
        ["executor.kind=inline", "tracking.enabled=false", "episodes_per_task=1"],
    )
    summary = execute(plan_run(cfg, tmp_path / "run"))
    assert summary.stored == 4 and summary.errors == 0
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    assert set(eps.perturbation) == {"none", "image_noise"}
    assert (eps.steps == 300).all() and not eps.success.any()  # the no-op never pushes the T
    assert set(eps.instruction) == {"push the T-shaped block onto the T-shaped target"}
    steps = RunStore(tmp_path / "run").steps().to_pandas()
    diag = steps[steps.cell_id == "diagnose"]
    assert diag.e_img.notna().all() and len(diag) == 2 * -(-300 // 8)  # ceil(300 / 8) each


def test_an_episode_that_ends_is_read_from_final_obs_and_final_info() -> None:
    """lerobot's vector envs reset an ended episode in the same step (SAME_STEP): success and
    the last observation are then under final_info / final_obs, as lerobot-eval reads them."""
    import gymnasium as gym
    from gymnasium.vector import AutoresetMode

    from workers.envs.suites.lerobot_envs.env import _OneOfVector

    class FakeSucceedsAtThree(gym.Env):
        """FAKE: succeeds (and terminates) at its third step; the observation counts steps."""

        observation_space = gym.spaces.Dict(
            {
                "pixels": gym.spaces.Box(0, 255, (4, 4, 3), np.uint8),
                "agent_pos": gym.spaces.Box(-9, 9, (2,), np.float32),
            }
        )
        action_space = gym.spaces.Box(-1, 1, (2,), np.float32)

        def reset(self, seed=None, options=None):
            super().reset(seed=seed)
            self.t = 0
            return self._obs(), {"is_success": False}

        def _obs(self):
            return {
                "pixels": np.full((4, 4, 3), self.t, np.uint8),
                "agent_pos": np.array([self.t, 0], np.float32),
            }

        def step(self, action):
            self.t += 1
            return self._obs(), 0.0, self.t >= 3, False, {"is_success": self.t >= 3}

    vec = gym.vector.SyncVectorEnv([FakeSucceedsAtThree], autoreset_mode=AutoresetMode.SAME_STEP)
    env = _OneOfVector(vec)
    env.reset(seed=0)
    for t in (1, 2, 3):
        obs, _, terminated, _, info = env.step(np.zeros(2, np.float32))
        assert obs["agent_pos"][0] == t  # never the next episode's reset
        assert info["is_success"] == (t == 3) and terminated == (t == 3)
