"""SIMPLER's official protocol without SAPIEN: the episode lists against the scripts' counts,
the robot rotation, the action conventions, the asset pre-flight, and the adapter driving a fake
ManiSkill2_real2sim (tests/doubles/fake_simpler_sim.py) in process and through an env server. The real simulator's
tests are in test_simpler_sim.py (they need a checkout and Vulkan)."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline.execution.runner import plan_run
from pipeline.planning.config import ConfigError, load_config
from workers.envs.suites.simpler import assets as sa
from workers.envs.suites.simpler import grids, vulkan_cpu
from workers.envs.suites.simpler import protocol as sp
from workers.envs.suites.simpler.assets import missing_assets
from workers.envs.suites.simpler.env import SimplerEnv

ROOT = Path(__file__).resolve().parents[3]
FAKE = ROOT / "tests" / "doubles" / "fake_simpler_sim.py"
DRAWER = "google_robot_open_top_drawer/visual_matching"


def test_episode_lists_have_the_official_counts() -> None:
    n = {name: {s: len(e) for s, e in t.setups.items()} for name, t in grids.TASKS.items()}
    coke = [k for k in n if "coke_can" in k]
    assert sum(n[k]["visual_matching"] for k in coke) == 300  # 3 orientations x 4 URDF x 25
    assert sum(n[k]["variant_agg"] for k in coke) == 675  # 3 x 9 variants x 25
    assert n["google_robot_move_near"] == {"visual_matching": 240, "variant_agg": 480}
    drawers = [k for k in n if k.endswith("_drawer") and "apple" not in k]
    assert len(drawers) == 6
    assert sum(n[k]["visual_matching"] for k in drawers) == 216
    assert sum(n[k]["variant_agg"] for k in drawers) == 378
    assert n["google_robot_place_apple_in_closed_top_drawer"] == {
        "visual_matching": 108,
        "variant_agg": 189,
    }
    assert all(n[k] == {"visual_matching": 24} for k in n if k.startswith("widowx"))
    steps = {name: t.max_steps for name, t in grids.TASKS.items()}
    assert steps["google_robot_move_near"] == 80 and steps["google_robot_close_top_drawer"] == 113
    assert steps["google_robot_place_apple_in_closed_top_drawer"] == 200
    assert steps["widowx_carrot_on_plate"] == 60 and steps["widowx_put_eggplant_in_basket"] == 120
    for task in grids.TASKS.values():  # every episode distinct within its list
        for eps in task.setups.values():
            assert len(
                {(e.env_id, e.scene, e.overlay, e.build, e.robot_xy, e.obj) for e in eps}
            ) == len(eps)


def test_drawer_visual_matching_follows_the_script_order() -> None:
    eps = grids.TASKS["google_robot_open_top_drawer"].setups["visual_matching"]
    first, last = eps[0], eps[-1]
    assert (first.overlay, first.robot_xy, first.robot_yaw) == (
        "open_drawer_a0.png",
        (0.644, -0.179),
        -0.03,
    )
    assert dict(first.build)["urdf_version"] == "" and dict(last.build)["urdf_version"].endswith(
        "cabinet_visual_matching_1"
    )
    assert last.overlay == "open_drawer_c2.png" and first.ray_tracing
    assert dict(first.build)["station_name"] == "mk_station_recolor"
    opts = first.reset_options()
    assert opts["obj_init_options"] == {"init_xy": [0.0, 0.0]}
    assert opts["robot_init_options"]["init_xy"] == [0.644, -0.179]
    carrot = grids.TASKS["widowx_carrot_on_plate"].setups["visual_matching"]
    assert [e.obj for e in carrot[:2]] == [("episode_id", 0), ("episode_id", 1)]


@pytest.mark.parametrize("yaw", [0.0, -0.09, -0.03, 0.4])
def test_robot_rotation_is_the_scripts_composition(yaw) -> None:
    from scipy.spatial.transform import Rotation

    # Pose(q=euler2quat(0, 0, yaw)) * Pose(q=[0, 0, 0, 1]), quaternions (w, x, y, z)
    expect = Rotation.from_euler("z", yaw) * Rotation.from_quat([0, 0, 1, 0])
    w, x, y, z = sp.base_quat(yaw)
    got = Rotation.from_quat([x, y, z, w])
    assert np.allclose(got.as_matrix(), expect.as_matrix(), atol=1e-12)
    if yaw == -0.09:  # the value SimplerEnv's move-near scripts produce
        assert np.allclose(sp.base_quat(yaw), (0.044985, 0, 0, 0.998988), atol=1e-6)


def test_action_conventions() -> None:
    r, p, y = 0.1, -0.2, 0.3
    a = np.array([0.01, 0.02, 0.03, r, p, y, 0.5])
    # roll-pitch-yaw (sxyz): R = Rz(y) Ry(p) Rx(r), written out independently of scipy
    cx, sx, cy, sy, cz, sz = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    m = rz @ ry @ rx
    angle = np.arccos((np.trace(m) - 1) / 2)
    axis = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) / (2 * np.sin(angle))
    g = sp.to_sim_action(a, "google", "rpy", binarize=False)
    assert np.allclose(g[3:6], axis * angle) and np.array_equal(g[:3], a[:3])
    assert np.array_equal(sp.to_sim_action(a, "google", "axis_angle", False)[3:6], a[3:6])
    assert sp.to_sim_action(np.r_[a[:6], 3.0], "google", "axis_angle", False)[6] == 1.0  # relative
    assert sp.to_sim_action(np.r_[a[:6], -0.2], "google", "axis_angle", False)[6] == -0.2
    assert sp.to_sim_action(np.r_[a[:6], 0.3], "widowx", "rpy", True)[6] == 1.0  # open
    assert sp.to_sim_action(np.r_[a[:6], -0.3], "widowx", "rpy", True)[6] == -1.0  # closed
    assert sp.to_sim_action(np.r_[a[:6], 0.3], "widowx", "rpy", False)[6] == 0.3
    with pytest.raises(ValueError, match="rotation='quat'"):
        sp.to_sim_action(a, "google", "quat", False)


def _checkout(tmp_path: Path, tasks: list[str]) -> Path:
    """A fake checkout: the fake envs as its package and, under data/, every file these tasks
    need."""
    root = tmp_path / "ManiSkill2_real2sim"
    package = root / "mani_skill2_real2sim"
    (package / "envs").mkdir(parents=True)
    (package / "__init__.py").touch()
    shutil.copyfile(FAKE, package / "envs" / "__init__.py")
    data = root / "data"
    keys = {"custom/info_pick_custom_v0.json": ["apple", "blue_plastic_bottle"]}
    for name in set(sa.MODEL_JSONS.values()) | set(keys):
        (data / name).parent.mkdir(parents=True, exist_ok=True)
        (data / name).write_text(json.dumps({k: {} for k in keys.get(name, [])}))
    for task_id in tasks:
        task, setup = grids.split_task_id(task_id)
        for ep in task.setups[setup]:
            for path in sa.episode_assets(ep, keys):
                f = data / path.replace("textured.*", "textured.glb")
                f.parent.mkdir(parents=True, exist_ok=True)
                f.touch()
    return root


def test_asset_preflight_names_the_missing_files(tmp_path) -> None:
    carrot = "widowx_carrot_on_plate/visual_matching"
    root = _checkout(tmp_path, [DRAWER, carrot])
    data = root / "data"
    eps = grids.TASKS["widowx_carrot_on_plate"].setups["visual_matching"]
    assert missing_assets(data, eps) == []
    (data / "hab2_bench_assets/stages/bridge_table_1_v1.glb").unlink()  # >= 4 MiB upstream
    (data / "custom/models/bridge_plate_objaverse_larger/textured.glb").unlink()
    assert missing_assets(data, eps) == [
        "hab2_bench_assets/stages/bridge_table_1_v1.glb",
        "custom/models/bridge_plate_objaverse_larger/textured.{obj,dae,glb}",
    ]
    # drawers load no object: a model folder's visual may be absent, its collision.obj not
    (data / "custom/models/apple/textured.glb").unlink(missing_ok=True)
    drawer_eps = grids.TASKS["google_robot_open_top_drawer"].setups["visual_matching"]
    assert missing_assets(data, drawer_eps) == []
    (data / "custom/models/apple/collision.obj").unlink()
    assert missing_assets(data, drawer_eps) == ["custom/models/apple/collision.obj"]


def test_the_run_is_refused_before_any_work(tmp_path, monkeypatch) -> None:
    root = _checkout(tmp_path, [DRAWER])
    (root / "data/real_inpainting/open_drawer_b1.png").unlink()
    # the runtime check (SAPIEN, a renderer) belongs to the env server's Python: not here
    monkeypatch.setattr(SimplerEnv, "check_runtime", classmethod(lambda cls, **p: None))
    base = ["tracking.enabled=false", "env.python=null", f"env.params.maniskill2_real2sim={root}"]
    smoke = ROOT / "conf" / "simpler_smoke.yaml"
    cfg = load_config(smoke, [*base, f"env.tasks=[{DRAWER}]", "episodes_per_task=4"])
    plan_run(cfg, tmp_path / "ok")  # the first 4 episodes need only a0..b0
    cfg = load_config(smoke, [*base, f"env.tasks=[{DRAWER}]", "episodes_per_task=5"])
    with pytest.raises(ConfigError, match=r"assets missing .*real_inpainting/open_drawer_b1.png"):
        plan_run(cfg, tmp_path / "r")
    cfg = load_config(smoke, [*base, f"env.tasks=[{DRAWER}]", "episodes_per_task=37"])
    with pytest.raises(ConfigError, match=r"episodes_per_task=37: .*have 36 episodes"):
        plan_run(cfg, tmp_path / "r")
    cfg = load_config(smoke, [*base, "env.tasks=[google_robot_open_top_drawer/nope]"])
    with pytest.raises(ConfigError, match=r"not in suite 'simpler'.*visual_matching"):
        plan_run(cfg, tmp_path / "r")
    (root / "data/real_inpainting/open_drawer_b1.png").touch()
    monkeypatch.setattr(vulkan_cpu, "resolve", lambda *a: "lavapipe")
    cfg = load_config(smoke, [*base, f"env.tasks=[{DRAWER}]", "env.params.shader=official"])
    with pytest.raises(ConfigError, match=r"shader='official': ray tracing .* lavapipe"):
        plan_run(cfg, tmp_path / "r")
    cfg = load_config(smoke, [*base, "env.params.shader=fancy"])
    with pytest.raises(ConfigError, match=r"env.params.shader='fancy': one of"):
        plan_run(cfg, tmp_path / "r")
    assert not (tmp_path / "r").exists()


def _run(env, task_id: str, episode: int, n: int, action: np.ndarray) -> list:
    obs = env.reset(task_id, episode, seed=123)
    seen = [(obs, obs.status.instruction)]
    for _ in range(n):
        obs = env.step(action)
        seen.append((obs, obs.status.instruction))
    return seen


def test_adapter_builds_resets_and_steps_as_the_evaluator(tmp_path, monkeypatch) -> None:
    root = _checkout(
        tmp_path, [DRAWER, "google_robot_place_apple_in_closed_top_drawer/visual_matching"]
    )
    monkeypatch.syspath_prepend(str(root))
    monkeypatch.delitem(sys.modules, "mani_skill2_real2sim", raising=False)
    monkeypatch.delitem(sys.modules, "mani_skill2_real2sim.envs", raising=False)
    env = SimplerEnv(
        maniskill2_real2sim=str(root), renderer="gpu", shader="official", rotation="rpy"
    )
    from mani_skill2_real2sim.envs import LOG

    seen = _run(env, DRAWER, 3, 113, np.array([0.01, 0, 0, 0, 0, 0.2, 0.5]))
    make, reset = LOG[0], LOG[1]
    assert make["env_id"] == "OpenTopDrawerCustomInScene-v0" and make["shader_dir"] == "rt"
    assert (
        make["control_freq"] == 3
        and make["sim_freq"] == 513
        and env._env.spec.max_episode_steps == 113
    )
    assert make["control_mode"] == sp.GOOGLE_CONTROL and make["scene_name"] == "dummy_drawer"
    assert make["rgb_overlay_path"].endswith("real_inpainting/open_drawer_b0.png")  # episode 3
    assert (
        make["rgb_overlay_cameras"] == ["overhead_camera"]
        and make["station_name"] == "mk_station_recolor"
    )
    assert reset["seed"] is None  # the env's own seed, as the evaluator
    assert reset["options"]["robot_init_options"]["init_xy"] == [0.652, 0.009]
    assert np.allclose(LOG[2]["action"][3:6], [0, 0, 0.2])  # yaw 0.2 -> axis-angle about z
    assert seen[0][0].images["image"].shape == (512, 640, 3) and seen[0][0].state.shape == (8,)
    last = seen[-1][0].status
    assert last.done and last.steps == 113
    assert not last.success  # success held at steps 3-5 only: the final step's rule
    assert last.info.init_state_id.startswith(f"{DRAWER}/urdf_none/open_drawer_b0")
    assert env.render_backend == "sapien-vulkan-gpu/rt"
    # any_step: the episode ends at the first success
    env2 = SimplerEnv(
        maniskill2_real2sim=str(root), renderer="gpu", shader="ibl", success_rule="any_step"
    )
    st = env2.reset(DRAWER, 0, seed=0).status
    while not st.done:
        st = env2.step(np.zeros(7)).status
    assert st.success and st.steps == 3 and LOG[-1]["op"] != "make"
    assert "shader_dir" not in [e for e in LOG if e["op"] == "make"][-1]  # ibl: the default
    # the apple task's instruction changes at step 100, as the env says
    apple = _run(
        env, "google_robot_place_apple_in_closed_top_drawer/visual_matching", 0, 101, np.zeros(7)
    )
    assert apple[99][1] == "open top drawer" and apple[100][1] == "place apple into top drawer"
    with pytest.raises(ValueError, match=r"episode 36: .* has 36 official episodes"):
        env.reset(DRAWER, 36, seed=0)
    env.close()
    env2.close()


def test_through_an_env_server(tmp_path) -> None:
    """The adapter in an env server (this Python standing in for .venv-simpler): the wire
    carries the task list with its episode counts, the observation and the success rule."""
    from workers.envs.factory import make_env
    from workers.envs.server.client import ServerSpec

    root = _checkout(tmp_path, [DRAWER])
    log = tmp_path / "fake.jsonl"
    import os

    os.environ["FAKE_SIMPLER_LOG"] = str(log)
    try:
        env = make_env(
            "simpler",
            {"maniskill2_real2sim": str(root), "renderer": "gpu", "shader": "ibl"},
            ServerSpec(python=sys.executable),
        )
        spec = next(t for t in env.tasks() if t.task_id == DRAWER)
        assert spec.episodes_total == 36 and spec.max_steps == 113
        obs = env.reset(DRAWER, 0, seed=0)
        assert obs.images["image"].shape == (512, 640, 3)
        for _ in range(5):
            st = env.step(np.array([0, 0, 0, 0, 0, 0, 2.0])).status
        assert st.success and not st.done  # step 5: success holds, 108 steps to go
        env.close()
    finally:
        del os.environ["FAKE_SIMPLER_LOG"]
    entries = [json.loads(line) for line in log.read_text().splitlines()]
    steps = [e["action"] for e in entries if e["op"] == "step"]
    assert len(steps) == 5 and all(a[6] == 1.0 for a in steps)  # Google's gripper clipped to 1
