"""LIBERO env: task tables without a simulator, the openpi / OFT protocol, the Env contract,
lazy rendering.

Simulators are slow to build here (5-20 s each, ~0.1 s per camera render on OSMesa), so one
module-scoped env at 64 px (lazy rendering, the default) serves every simulator test, and one
more (``eager_env``: robosuite's camera observables, ``flip_images=False``) gives the reference
pictures to compare with.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from workers.envs.checks import check_env
from workers.envs.suites.libero.assets import LiberoSetupError, ensure_config_env
from workers.envs.suites.libero.env import LiberoEnv, quat_to_axis_angle, state_vector

SIZE = 64
# The openpi / OpenVLA-OFT protocol, written out here so a change of the defaults shows up.
PROTOCOL_MAX_STEPS = {
    "libero_spatial": 220,
    "libero_object": 280,
    "libero_goal": 300,
    "libero_10": 520,
}
ONE_PER_SUITE = [f"{suite}/0" for suite in PROTOCOL_MAX_STEPS]


def _benchmark_language(task_id: str) -> str:
    ensure_config_env()  # importing libero without its config would prompt on stdin
    from libero.libero import benchmark

    suite, index = task_id.split("/")
    return benchmark.get_benchmark(suite)().get_task(int(index)).language


def _assert_obs_shapes(env: LiberoEnv, obs) -> None:
    assert set(obs.images) == set(env.cameras) == {"agentview", "wrist"}
    for img in obs.images.values():
        assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8
        assert img.std() > 0  # a rendered scene, not a blank buffer
    assert obs.state.shape == (8,) and obs.state.dtype == np.float32
    assert np.isfinite(obs.state).all()


@pytest.fixture(scope="module")
def env():
    """One env for all simulator tests; counts the simulators it builds."""
    e = LiberoEnv(image_size=SIZE)
    assert e.lazy_render  # the default
    built: list = []
    make = e._make_sim

    def counting_make_sim(*args, **kwargs):
        built.append(make(*args, **kwargs))
        return built[-1]

    e._make_sim = counting_make_sim
    e.built = built
    yield e
    e.close()


@pytest.fixture(scope="module")
def eager_env():
    """The reference: robosuite renders every camera on every step (the pre-lazy path), and the
    pictures are left as robosuite gives them."""
    e = LiberoEnv(
        suites=["libero_spatial"],
        image_size=SIZE,
        flip_images=False,
        max_steps={"libero_spatial": 3},
        lazy_render=False,
    )
    yield e
    e.close()


@pytest.fixture
def gl_renders(monkeypatch) -> list[int]:
    """Counts MuJoCo renders (``mjr_render``, what every robosuite camera render calls)."""
    import mujoco

    calls: list[int] = []
    real = mujoco.mjr_render

    def counting(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(mujoco, "mjr_render", counting)
    return calls


# -- no simulator ------------------------------------------------------------------------------


@pytest.mark.slow
def test_suite_tasks_lists_40_tasks_without_importing_mujoco() -> None:
    code = (
        "import json, sys; from workers.envs.suites.libero.env import LiberoEnv;"
        "ts = LiberoEnv.suite_tasks();"
        "print(json.dumps({'tasks': [[t.task_id, t.suite, t.instruction, t.max_steps, t.name]"
        " for t in ts], 'sim_imported': [m for m in ('mujoco', 'robosuite') if m in sys.modules]}))"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=os.environ
    )
    assert r.returncode == 0, r.stderr[-2000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["sim_imported"] == []
    tasks = out["tasks"]
    assert len(tasks) == 40
    assert [t[0] for t in tasks] == [f"{s}/{i}" for s in PROTOCOL_MAX_STEPS for i in range(10)]
    for task_id, suite, instruction, max_steps, name in tasks:
        assert task_id.startswith(f"{suite}/")
        assert max_steps == PROTOCOL_MAX_STEPS[suite]
        assert instruction == _benchmark_language(task_id)
        assert name and instruction.strip()
    assert tasks[0][2] == (
        "pick up the black bowl between the plate and the ramekin and place it on the plate"
    )


@pytest.mark.slow
def test_suite_tasks_params_select_suites_and_override_max_steps() -> None:
    tasks = LiberoEnv.suite_tasks(suites=["libero_10"], max_steps={"libero_10": 600})
    assert [t.task_id for t in tasks] == [f"libero_10/{i}" for i in range(10)]
    assert {t.max_steps for t in tasks} == {600}
    with pytest.raises(ValueError, match=r"max_steps\['libero_90'\] must be set"):
        LiberoEnv.suite_tasks(suites=["libero_90"])
    assert len(LiberoEnv.suite_tasks(suites=["libero_90"], max_steps={"libero_90": 400})) == 90


@pytest.mark.parametrize(
    ("params", "message"),
    [
        ({"image_size": 0}, "image_size must be an int > 0"),
        ({"image_size": -8}, "image_size must be an int > 0"),
        (
            {"protocol": "oft"},
            r"protocol='oft' is not a LIBERO protocol; choose one of \['openpi', 'lerobot'\]",
        ),
        (
            {"suites": ["libero_spatail"]},
            r"suites: \['libero_spatail'\] empty, unknown or repeated \(did you mean "
            r"libero_spatial\?\); valid: .*libero_spatial",
        ),
        (
            {"cameras": ["agentview", "top"]},
            r"cameras=.*use distinct names from \['agentview', 'wrist'\]",
        ),
        ({"num_noops": -1}, "num_noops must be an int >= 0"),
        ({"max_steps": {"libero_goal": 0}}, r"max_steps\['libero_goal'\] must be an int > 0"),
        ({"max_steps": {"libero_gaol": 300}}, r"max_steps: \['libero_gaol'\] unknown suites"),
        ({"suites": ["libero_10", "libero_10"]}, "unknown or repeated"),
    ],
)
def test_bad_params_are_named(params, message) -> None:
    with pytest.raises(ValueError, match=message):
        LiberoEnv(**params)


@pytest.mark.slow
def test_unknown_task_id_lists_valid_ones() -> None:
    env = LiberoEnv(suites=["libero_goal"], image_size=SIZE)
    with pytest.raises(
        ValueError, match=r"task_id='libero_goal/10' unknown; valid: .*'libero_goal/9'"
    ):
        env.reset("libero_goal/10", 0, 0)
    with pytest.raises(ValueError, match="unknown"):
        env.reset("libero_spatial/0", 0, 0)  # a suite not chosen
    assert env._sim is None  # refused before building a simulator
    with pytest.raises(RuntimeError, match="before reset"):
        env.step(np.zeros(7))


def test_missing_config_names_the_fix(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("LIBERO_CONFIG_PATH", str(tmp_path))
    with pytest.raises(LiberoSetupError, match=r"python -m workers.envs.suites.libero.assets"):
        LiberoEnv.suite_tasks()


def test_axis_angle_follows_openpi_convention() -> None:
    half = math.pi / 4
    q = np.array([0.0, 0.0, math.sin(half), math.cos(half)])  # 90 deg about z, (x, y, z, w)
    np.testing.assert_allclose(quat_to_axis_angle(q), [0, 0, math.pi / 2], atol=1e-12)
    assert q[3] == math.cos(half)  # input untouched
    np.testing.assert_allclose(quat_to_axis_angle(np.array([0.0, 0, 0, 1])), np.zeros(3))
    # 270 deg about z stays 3pi/2 (no wrap to -pi/2): the numbers openpi's data holds
    half = 3 * math.pi / 4
    q = np.array([0.0, 0.0, math.sin(half), math.cos(half)])
    np.testing.assert_allclose(quat_to_axis_angle(q), [0, 0, 3 * math.pi / 2], atol=1e-12)


def test_state_vector_is_pos_axis_angle_gripper() -> None:
    raw = {
        "robot0_eef_pos": np.array([0.1, 0.2, 0.3]),
        "robot0_eef_quat": np.array([1.0, 0.0, 0.0, 0.0]),  # 180 deg about x
        "robot0_gripper_qpos": np.array([0.04, -0.04]),
    }
    s = state_vector(raw)
    assert s.dtype == np.float32 and s.shape == (8,)
    np.testing.assert_allclose(s, [0.1, 0.2, 0.3, math.pi, 0, 0, 0.04, -0.04], rtol=1e-6)


# -- with a simulator ----------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.sim
def test_check_env_passes_and_one_simulator_serves_all_episodes(env) -> None:
    check_env(env, task_id="libero_spatial/0", n_steps=2)
    assert len(env.built) == 1  # six resets of one task, one simulator


@pytest.mark.slow
@pytest.mark.sim
def test_lazy_images_equal_the_eager_ones_flipped_180_degrees(env, eager_env) -> None:
    """Same task, episode, seed and actions: the lazy env's images are robosuite's own camera
    observations (pixel for pixel), flipped on both axes (the eager path with
    ``flip_images=True`` applies the same ``[::-1, ::-1]``, ``LiberoEnv._finish``)."""
    actions = np.array(
        [[0.5, 0.3, 0, 0, 0, 0, -1], [0.2, -0.4, 0.3, 0, 0, 0.2, 1], [-0.3, 0, -0.2, 0, 0.1, 0, 1]],
        dtype=np.float32,
    )
    # the eager episode first, whole: robosuite renders inside its steps with the current GL
    # context (its own since its reset); the lazy env makes its own current when it renders
    raw = [eager_env.reset("libero_spatial/0", 2, seed=5)]
    raw += [eager_env.step(a) for a in actions]
    lazy = [env.reset("libero_spatial/0", 2, seed=5)]  # after six episodes of check_env
    lazy += [env.step(a) for a in actions]
    for i, (r, f) in enumerate(zip(raw, lazy, strict=True)):
        np.testing.assert_array_equal(f.state, r.state)
        for cam in ("agentview", "wrist"):
            assert np.array_equal(f.images[cam], r.images[cam][::-1, ::-1]), (i, cam)
            assert not np.array_equal(f.images[cam], r.images[cam])
            assert not np.array_equal(f.images[cam], r.images[cam][::-1])  # both axes
    assert not np.array_equal(lazy[0].images["wrist"], lazy[-1].images["wrist"])  # it moved
    # the eager env shows max_steps is a param and ends the episode
    last = raw[-1].status
    assert {t.max_steps for t in eager_env.tasks()} == {3}
    assert last.done and not last.success and last.steps == 3
    with pytest.raises(RuntimeError, match="after the episode is done"):
        eager_env.step(np.zeros(7))


@pytest.mark.slow
@pytest.mark.sim
def test_lazy_env_renders_only_the_images_read(env, gl_renders) -> None:
    env.reset("libero_spatial/0", 4, seed=0)
    first = env.step(np.array([0.5, 0, 0, 0, 0, 0, -1], dtype=np.float32))
    assert env._sim.env.timestep == 11  # ten no-ops and one step ran...
    assert gl_renders == []  # ...and hard reset, init state, no-ops and step rendered nothing
    for _ in range(7):  # an open-loop chunk: nobody reads these images
        obs = env.step(np.array([0, 0.5, 0, 0, 0, 0, -1], dtype=np.float32))
    assert gl_renders == []
    wrist = obs.images["wrist"]  # the inference step reads them
    assert len(gl_renders) == 1 and obs.images.rendered == ("wrist",)
    assert obs.images["wrist"] is wrist and len(gl_renders) == 1  # cached
    agentview = obs.images["agentview"]
    assert len(gl_renders) == 2
    for img in (wrist, agentview):
        assert img.shape == (SIZE, SIZE, 3) and img.dtype == np.uint8 and img.std() > 0
    # an earlier observation of the episode still shows its own moment
    assert not np.array_equal(first.images["wrist"], wrist)
    assert len(gl_renders) == 3
    env.reset("libero_spatial/0", 4, seed=0)  # a hard reset: a new simulator
    with pytest.raises(RuntimeError, match="before the last reset"):
        _ = first.images["agentview"]
    assert len(gl_renders) == 3


@pytest.mark.slow
@pytest.mark.sim
@pytest.mark.parametrize("task_id", ONE_PER_SUITE)
def test_episode_follows_the_protocol(env, task_id) -> None:
    suite = task_id.split("/")[0]
    before = list(env.built)
    obs = env.reset(task_id, 53, seed=7)  # 50 init states per task: wraps to init 3

    spec = next(t for t in env.tasks() if t.task_id == task_id)
    st = obs.status
    assert st.task_id == task_id and spec.suite == suite
    assert spec.max_steps == PROTOCOL_MAX_STEPS[suite]
    assert st.instruction == _benchmark_language(task_id)
    assert st.info.init_state_id == f"{task_id}/init3"
    assert st.steps == 0 and not st.done and not st.success
    assert env._sim.env.timestep == 10  # the ten no-ops ran in the simulator, uncounted
    _assert_obs_shapes(env, obs)
    raw = env._sim.env._get_observations()
    np.testing.assert_allclose(obs.state[:3], raw["robot0_eef_pos"], rtol=1e-6)
    np.testing.assert_allclose(obs.state[6:], raw["robot0_gripper_qpos"], rtol=1e-5, atol=1e-7)

    start = obs.state.copy()
    for i in range(3):
        obs = env.step(np.array([0.5, 0, 0, 0, 0, 0, -1], dtype=np.float32))
        assert obs.status.steps == i + 1
    _assert_obs_shapes(env, obs)
    assert obs.state[0] > start[0] + 1e-3  # +x command moved the end effector along +x
    assert not obs.status.done

    if suite != "libero_spatial":  # switching task closed the previous simulator
        assert len(env.built) == len(before) + 1
        assert not hasattr(before[-1], "env")  # LIBERO's close() drops its inner env


@pytest.mark.slow
@pytest.mark.sim
def test_scene_perturbations_and_bit_identical_none(env) -> None:
    """Scene kinds on LIBERO: the table (libero_10/0: the living room's unnamed table mesh) recoloured
    through its material, the objects jittered; ``none`` right after them is the unperturbed
    episode to the bit. Reuses the module's simulator (the last task above)."""
    from workers.envs.wrappers.perturbation_grammar import parse
    from workers.envs.wrappers.perturbations import PerturbedEnv

    task = "libero_10/0"
    kinds = ["table_color:0.8", "init_jitter:0.02"]
    pe = PerturbedEnv(env, [None, *map(parse, kinds)])
    assert {t.task_id for t in pe.tasks()} >= {task, *(f"{task}@{k}" for k in kinds)}

    last = [None]  # the last episode's status

    def episode(task_id: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        obs = pe.reset(task_id, 4, seed=7)
        last[0] = obs.status
        first = obs.images["agentview"].copy()
        qpos = env._sim.env.sim.data.qpos.copy()
        obs = pe.step(np.array([0.5, 0, 0, 0, 0, 0, -1], dtype=np.float32))
        return first, obs.images["wrist"].copy(), obs.state.copy(), qpos

    plain = episode(task)
    tinted = episode(f"{task}@table_color:0.8")
    assert np.array_equal(tinted[3], plain[3]) and np.array_equal(tinted[2], plain[2])
    assert tinted[0].mean() < plain[0].mean() - 5  # the table darkened toward brown
    jittered = episode(f"{task}@init_jitter:0.02")
    assert last[0].info.init_state_id == f"{task}/init4@init_jitter:0.02"
    assert last[0].task_id == f"{task}@init_jitter:0.02"  # the wrapper's id
    moved = np.abs(jittered[3] - plain[3])
    assert 1e-4 < moved.max() < 0.05  # objects moved by centimetres, nothing flew
    again = episode(task)
    assert last[0].info.init_state_id == f"{task}/init4"
    for a, b in zip(again, plain, strict=True):
        assert np.array_equal(a, b)
