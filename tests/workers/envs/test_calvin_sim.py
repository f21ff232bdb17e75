"""The real CALVIN env (calvin_env + PyBullet) in its env server, from Python 3.11.

Skipped, with the reason, where `make setup-calvin` has not built .venv-calvin or CALVIN_ENV
does not point at a calvin_env checkout (calvin_env is not on a package index)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from itertools import product
from pathlib import Path

import numpy as np
import pytest

from workers.envs.checks import check_env
from workers.envs.server.client import EnvServerClient, ServerSpec
from workers.envs.suites.calvin.checkout import find_checkout
from workers.envs.suites.calvin.sequences import load_sequences

ROOT = Path(__file__).resolve().parents[3]
PYTHON = Path(os.environ.get("IDR_CALVIN_PYTHON", ROOT / ".venv-calvin" / "bin" / "python"))
CHECKOUT = os.environ.get("CALVIN_ENV")
ENTRY = "workers.envs.suites.calvin.env:CalvinEnv"


def _checkout_problem() -> str | None:
    """Why CALVIN_ENV cannot build the env here (the adapter's own check), or None."""
    try:
        find_checkout(CHECKOUT)
    except ValueError as e:
        return str(e)
    return None


if not PYTHON.exists():
    pytestmark = pytest.mark.skip(reason=f"no CALVIN interpreter at {PYTHON}: make setup-calvin")
elif not CHECKOUT or not Path(CHECKOUT, "calvin_env").is_dir():
    pytestmark = pytest.mark.skip(reason="CALVIN_ENV does not point at a calvin_env checkout")
elif problem := _checkout_problem():
    pytestmark = pytest.mark.skip(reason=problem)
else:
    pytestmark = pytest.mark.sim

SERVER = ServerSpec(str(PYTHON), timeout_s=120)
OPEN, CLOSE = 1.0, -1.0


@pytest.fixture(scope="module")
def env():
    e = EnvServerClient(ENTRY, {"renderer": "tiny"}, SERVER)
    yield e
    e.close()


def test_the_calvin_env_passes_the_env_contract(env):
    check_env(env, run_to_horizon=True)  # the horizon: the first subtask's 360 steps
    assert env.render_backend == "pybullet-tiny" and env.hello["python"].startswith("3.11")


def test_a_noop_sequence_fails_its_first_subtask_after_360_steps(env):
    obs = env.reset("scene_D", 0, 0)
    assert obs.status.instruction == "take the blue block and rotate it to the right"
    assert obs.images["rgb_static"].shape == (200, 200, 3)
    assert obs.images["rgb_gripper"].shape == (84, 84, 3) and obs.state.shape == (15,)
    while not obs.status.done:
        obs = env.step(np.array([0, 0, 0, 0, 0, 0, OPEN]))
    st = obs.status
    assert (st.steps, st.subtasks_done, st.success) == (360, 0, False)
    assert st.info.failure_cause == "subtask_budget"
    assert "subtask 1/5 'rotate_blue_block_right'" in st.info.failure_reason


def _go(env, goal, gripper, steps, orn=(np.pi, 0.0, np.pi / 2)):
    """A proportional controller on the robot's target pose (privileged): the actions are
    relative, in units of 0.02 m and 0.05 rad, as a policy's. The last status."""
    st = None
    for _ in range(steps):
        p = env._call("privileged")
        d_pos = (np.asarray(goal) - p["target_pos"]) / 0.02
        d_orn = ((np.asarray(orn) - p["target_orn"] + np.pi) % (2 * np.pi) - np.pi) / 0.05
        st = env.step(np.r_[np.clip(d_pos, -1, 1), np.clip(d_orn, -1, 1), gripper]).status
        if st.subtasks_done:
            break
    return st


def test_a_scripted_controller_opens_the_drawer_and_the_oracle_sees_it(env):
    seqs = load_sequences()
    e = next(i for i, (cond, tasks) in enumerate(seqs) if tasks[0] == "open_drawer")
    assert env.reset("scene_D", e, 0).status.instruction == "pull the handle to open the drawer"
    handle = np.array([0.18, -0.25, 0.36])  # the drawer's handle bar (found with rayTest)
    _go(env, handle + np.array([0, 0, 0.10]), OPEN, 60)
    _go(env, handle, OPEN, 40)
    _go(env, handle, CLOSE, 15)
    st = _go(env, handle - np.array([0, 0.20, 0]), CLOSE, 80)
    assert st.subtasks_done == 1 and not st.done, st.info.failure_reason
    assert st.steps < 360
    # the next subtask's instruction; the policy is reset there (policy_reset_per_subtask)
    assert st.instruction != "pull the handle to open the drawer"
    assert env.policy_reset_per_subtask is True


def test_a_sequence_does_not_depend_on_what_ran_before(env):
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (20, 7))

    def run() -> tuple[list[np.ndarray], np.ndarray]:
        env.reset("scene_D", 7, 0)
        states = [env.step(a).state for a in actions[:-1]]
        last = env.step(actions[-1])
        return [*states, last.state], last.images["rgb_static"]

    first = run()
    for e in (0, 7):
        env.reset("scene_D", e, 0)
        for a in rng.uniform(-1, 1, (150, 7)):  # disturb contacts, solver and sleeping state
            env.step(a)
        again = run()
        assert all(np.array_equal(a, b) for a, b in zip(first[0], again[0], strict=True))
        assert np.array_equal(first[1], again[1])
    fresh = EnvServerClient(ENTRY, {"renderer": "tiny"}, SERVER)  # a new process: no history at all
    try:
        fresh.reset("scene_D", 7, 0)
        states = [fresh.step(a).state for a in actions]
        assert all(np.array_equal(a, b) for a, b in zip(first[0], states, strict=True))
    finally:
        fresh.close()


_SAME_AS_ENV_STEP = textwrap.dedent(
    """
    import json, sys
    import numpy as np
    from workers.envs.suites.calvin.env import CalvinEnv, binarize_gripper
    env = CalvinEnv(renderer="tiny")
    actions = np.random.default_rng(1).uniform(-1, 1, (30, 7))
    env.reset("scene_D", 3, 0)
    ours = []
    for a in actions:
        obs = env.step(a)
        ours.append((obs.state, obs.images["rgb_static"], obs.images["rgb_gripper"]))
    env.reset("scene_D", 3, 0)
    same = True
    for a, (state, static, gripper) in zip(actions, ours):
        o, _, _, _ = env._env.step(binarize_gripper(a))  # calvin_env's own step
        same &= np.array_equal(np.float32(o["robot_obs"]), state)
        same &= np.array_equal(o["rgb_obs"]["rgb_static"], static)
        same &= np.array_equal(o["rgb_obs"]["rgb_gripper"], gripper)
    env.close()
    print(json.dumps({"same": bool(same)}))
    """
)


def test_lazy_stepping_gives_what_calvins_own_step_gives():
    """Our step is calvin_env's ``env.step`` without its camera rendering (images rendered when
    read): the same states and the same pixels."""
    r = subprocess.run(
        [str(PYTHON), "-c", _SAME_AS_ENV_STEP],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert json.loads(r.stdout.strip().splitlines()[-1]) == {"same": True}


def _calvin_clone() -> Path | None:
    for root in (os.environ.get("CALVIN_ROOT"), str(Path(CHECKOUT or ".").parent)):
        if root and Path(root, "calvin_models/calvin_agent/evaluation").is_dir():
            return Path(root)
    return None


@pytest.mark.skipif(_calvin_clone() is None, reason="no mees/calvin clone around CALVIN_ENV")
def test_the_shipped_sequences_regenerate_from_the_official_generator():
    """A sample of initial states: their sequences as the unmodified multistep_sequences.py
    draws them (get_sequences(1000) itself takes minutes)."""
    import importlib.util
    import types
    from contextlib import contextmanager

    @contextmanager
    def temp_seed(seed):  # what calvin_agent.evaluation.utils.temp_seed does
        state = np.random.get_state()
        np.random.seed(seed)
        try:
            yield
        finally:
            np.random.set_state(state)

    saved = {
        k: sys.modules.get(k)
        for k in ("calvin_agent", "calvin_agent.evaluation", "calvin_agent.evaluation.utils")
    }
    try:
        for name in ("calvin_agent", "calvin_agent.evaluation"):
            sys.modules[name] = types.ModuleType(name)
        utils = types.ModuleType("calvin_agent.evaluation.utils")
        utils.temp_seed = temp_seed  # its only import; the real one pulls in torch
        sys.modules["calvin_agent.evaluation.utils"] = utils
        path = _calvin_clone() / "calvin_models/calvin_agent/evaluation/multistep_sequences.py"
        spec = importlib.util.spec_from_file_location("calvin_multistep_sequences", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        for k, v in saved.items():
            if v is None:
                sys.modules.pop(k, None)
            else:
                sys.modules[k] = v
    # the initial states in get_sequences' order, and how many sequences each gets of 1000
    conditions = {
        "led": [0, 1], "lightbulb": [0, 1], "slider": ["right", "left"],
        "drawer": ["closed", "open"], "red_block": ["table", "slider_right", "slider_left"],
        "blue_block": ["table", "slider_right", "slider_left"],
        "pink_block": ["table", "slider_right", "slider_left"], "grasped": [0],
    }  # fmt: skip
    states = [
        dict(zip(conditions, v, strict=True))
        for v in product(*conditions.values())
        if v[4:7].count("table") in (1, 2)
        and v[4:7].count("slider_right") < 2
        and v[4:7].count("slider_left") < 2
    ]
    assert len(states) == 192
    counts = [len(c) for c in np.array_split(range(1000), len(states))]
    shipped = load_sequences()
    for i in (0, 1, 57, 191):
        drawn = module.get_sequences_for_state2((states[i], counts[i], i))
        ours = [tasks for cond, tasks in shipped if cond == states[i]]
        assert sorted(tuple(s) for s in drawn) == sorted(ours)


def test_the_smoke_preset_runs_end_to_end(tmp_path):
    """`idr-eval run conf/calvin_smoke.yaml`: no-op sequences fail their first subtask, the
    chain aggregation reports Avg Len 0, the renderer and the env server are recorded."""
    import pandas as pd

    from pipeline.execution.runner import execute, plan_run
    from pipeline.planning.config import load_config
    from pipeline.results.store import RunStore

    cfg = load_config(
        ROOT / "conf" / "calvin_smoke.yaml",
        [
            "tracking.enabled=false",
            "executor.kind=inline",
            "episodes_per_task=2",
            f"env.python={PYTHON}",
            "env.params.renderer=tiny",
        ],
    )
    summary = execute(plan_run(cfg, tmp_path / "run"))
    assert summary.stored == 2 and summary.errors == 0
    eps: pd.DataFrame = RunStore(tmp_path / "run").episodes().to_pandas()
    assert (eps.subtasks_done == 0).all() and (eps.steps == 360).all()
    assert (eps.failure == "subtask_budget").all() and (eps.render_backend == "pybullet-tiny").all()
    assert list(eps.sort_values("episode_index").instruction) == [
        "take the blue block and rotate it to the right",
        "press the button to turn off the led light",
    ]
    report = (tmp_path / "run" / "report.md").read_text()
    assert "Env protocol: calvin" in report and "| 0.00 [0.00, 0.00] |" in report
    meta = json.loads((tmp_path / "run" / "run.json").read_text())
    assert meta["env_server"]["python"].startswith("3.11")
