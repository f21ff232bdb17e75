"""MetaWorld's own env through the gymnasium suite (the zoo's second benchmark): rendered frames
as a camera, several tasks of one id, a sliced state, MuJoCo's render quality; the recorder
writes exactly the frames an evaluation of the same config shows."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from pipeline.execution.runner import plan_run
from pipeline.planning.config import ConfigError, config_from_dict
from workers.envs.checks import check_env
from workers.envs.factory import make_env
from workers.rendering import configure_rendering

configure_rendering()  # before metaworld imports mujoco
pytest.importorskip("metaworld", reason="metaworld is not installed (make setup installs it)")
pytestmark = [pytest.mark.sim]

CONF = Path(__file__).resolve().parents[3] / "conf"
ZOO = yaml.safe_load((CONF / "zoo" / "metaworld.yaml").read_text())["env"]


def test_the_zoo_metaworld_block_is_five_tasks_of_one_env_at_96px() -> None:
    env = make_env("gymnasium", ZOO["params"])
    try:
        check_env(env)
        tasks = {t.task_id: t for t in env.tasks()}
        assert list(tasks) == ZOO["tasks"]
        assert tasks["drawer-open-v3"].instruction == "Open a drawer"
        assert all(t.max_steps == 150 for t in tasks.values())
        assert env.cameras == ("image",) and env.state_dim == 4 and env.action_dim == 4
        a = env.reset("drawer-open-v3", 0, seed=0)
        assert a.status.instruction == "Open a drawer"
        assert a.images["image"].shape == (96, 96, 3) and a.images["image"].dtype == np.uint8
        full = env.raw_observation["state"]
        assert full.shape == (39,) and np.array_equal(a.state, full[:4].astype(np.float32))
        assert env._env.unwrapped.model.vis.quality.shadowsize == 512  # render_quality applied
        objects0 = full[4:7].copy()
        again = env.reset("drawer-open-v3", 0, seed=0)
        assert np.array_equal(again.images["image"], a.images["image"])  # seeded: the same scene
        env.reset("drawer-open-v3", 1, seed=0)
        assert not np.allclose(env.raw_observation["state"][4:7], objects0)  # another init
        assert env.reset("button-press-v3", 0, seed=0).status.instruction == "Press a button"
    finally:
        env.close()


@pytest.mark.parametrize("drop", ["close", "collect"])
def test_an_env_keeps_its_frames_when_another_env_in_the_process_goes(drop) -> None:
    """Two MuJoCo envs in one process (the recorder after an earlier test's env, one env per
    task): the other one closed, or dropped and collected while its GL context is current,
    must not blank this one's frames (its framebuffer was deleted under the wrong context)."""
    import gc

    a = make_env("gymnasium", ZOO["params"])
    try:
        before = a.reset("button-press-v3", 7, seed=0).images["image"]
        b = make_env("gymnasium", ZOO["params"])
        b.reset("button-press-v3", 7, seed=0)  # b's context is the current one now
        a.reset("button-press-v3", 7, seed=0)
        if drop == "close":
            b.close()
        del b
        gc.collect()
        after = a.reset("button-press-v3", 7, seed=0).images["image"]
        assert after.mean() > 50  # not black
        assert np.array_equal(after, before)
        a.step(np.zeros(4, dtype=np.float32))
        assert a.reset("button-press-v3", 7, seed=0).images["image"].mean() > 50
    finally:
        a.close()


@pytest.mark.slow
def test_the_recorder_writes_the_frames_an_evaluation_sees(tmp_path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from training.metaworld_demos import record

    stats = record(tmp_path / "ds", episodes=1, tasks=["button-press-v3"], first_episode=7)
    assert stats["button-press-v3"]["episodes"] == 1
    ds = LeRobotDataset("local/zoo_metaworld", root=tmp_path / "ds")
    assert (
        ds.meta.total_episodes == 1 and ds.meta.total_frames == stats["button-press-v3"]["frames"]
    )
    first = ds[0]
    env = make_env("gymnasium", ZOO["params"])
    try:
        obs = env.reset("button-press-v3", 7, seed=0)  # the recorder's first try: episode 7
    finally:
        env.close()
    image = (first["observation.image"].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    assert np.array_equal(image, obs.images["image"])
    assert np.allclose(first["observation.state"].numpy(), obs.state)
    assert first["task"] == "Press a button"


@pytest.mark.parametrize(
    ("change", "pattern"),
    [
        ({"render_quality": {"shadows": 1}}, r"render_quality.shadows: not a MuJoCo"),
        (
            {"kwargs": {"render_mode": None, "width": 96, "height": 96}},
            r"render_key: the env must render frames",
        ),
        ({"tasks": {"reach-v3": {"kwarg": {}}}}, r"tasks.reach-v3: unknown keys \['kwarg'\]"),
        ({"state": ["state[0:4]", "hand"]}, r"state: \['hand'\] not in"),
    ],
)
def test_bad_gymnasium_params_are_refused_before_any_work(tmp_path, change, pattern) -> None:
    cfg = config_from_dict(
        {
            "name": "bad",
            "backbone": {"kind": "noop", "params": {"action_dim": 4}},
            "env": {
                "suite": "gymnasium",
                "tasks": ZOO["tasks"][:1],
                "params": {**ZOO["params"], **change},
            },
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
        }
    )
    with pytest.raises(ConfigError, match=pattern):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()
