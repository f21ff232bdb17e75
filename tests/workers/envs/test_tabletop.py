"""The tabletop suite on robosuite: contract, experts, chain accounting, blind policies fail."""

from __future__ import annotations

import numpy as np
import pytest

pytestmark = [pytest.mark.sim, pytest.mark.slow]


@pytest.fixture(scope="module")
def env():
    from workers.rendering import configure_rendering

    configure_rendering()
    from workers.envs.suites.tabletop.env import TabletopEnv

    e = TabletopEnv(image_size=64, cameras=("agentview", "wrist"))
    yield e
    e.close()


def _run(env, task, episode, policy, seed=0):
    from workers.experts.tabletop import expert_action  # noqa: F401

    obs = env.reset(task, episode, seed)
    while not obs.status.done:
        obs = env.step(policy(obs.privileged))
    return obs.status


@pytest.mark.parametrize("task", ["pick_color", "stack_color", "organize"])
def test_contract(env, task) -> None:
    from workers.envs.checks import check_env

    check_env(env, task_id=task, n_steps=4)


@pytest.mark.parametrize(
    ("task", "episodes"), [("pick_color", 3), ("stack_color", 3), ("organize", 1)]
)
def test_expert_succeeds(env, task, episodes) -> None:
    from workers.experts.tabletop import expert_action

    spec = next(t for t in env.tasks() if t.task_id == task)
    for i in range(episodes):
        st = _run(env, task, 100 + i, expert_action)
        assert st.success, (
            f"{task} episode {100 + i}: expert failed after {st.steps} steps "
            f"({st.info.failure_reason})"
        )
        assert st.subtasks_done == spec.subtasks_total and st.steps < spec.max_steps


def test_expert_with_a_wider_place_tolerance_still_succeeds(env) -> None:
    """place_tol 2 cm (lower the held cube while still correcting xy): still a perfect expert."""
    from workers.experts.tabletop import TabletopExpertBackbone, expert_action

    for task, i in (("stack_color", 110), ("stack_color", 111), ("organize", 110)):
        st = _run(env, task, i, lambda p: expert_action(p, place_tol=0.02))
        assert st.success, f"{task} episode {i}: failed after {st.steps} steps ({st.info})"
    with pytest.raises(ValueError, match="place_tol"):
        TabletopExpertBackbone(place_tol=0.05)


def test_chain_stops_at_first_failure(env) -> None:
    """An expert told a wrong order puts two cubes right, then a wrong one: chain ends at 2/5."""
    from workers.experts.tabletop import expert_action

    def swapped(priv):
        order = list(priv["targets"])
        order[2], order[3] = order[3], order[2]
        return expert_action({**priv, "targets": order})

    st = _run(env, "organize", 7, swapped)
    assert not st.success and st.subtasks_done == 2 and st.done
    assert "put in the bin before" in st.info.failure_reason
    assert st.info.failure_cause == "wrong_order"


def test_chain_ends_when_a_subtask_overruns_its_budget(env) -> None:
    """Standing still: organize ends after subtask_budget steps, with that cause."""
    st = _run(env, "organize", 0, lambda p: np.array([0, 0, 0, 0, 0, 0, -1.0]))
    max_steps = next(t.max_steps for t in env.tasks() if t.task_id == "organize")
    assert not st.success and st.subtasks_done == 0 and st.steps == env.subtask_budget < max_steps
    assert st.info.failure_cause == "subtask_budget"
    assert "subtask 1 not done" in st.info.failure_reason
    # the next episode starts clean
    info = env.reset("organize", 1, 0).status.info
    assert info.failure_cause is None and info.failure_reason is None


def test_wrong_actions_fail_and_episode_ends_at_max_steps(env) -> None:
    st = _run(env, "pick_color", 0, lambda p: np.array([0, 0, 1.0, 0, 0, 0, -1.0]))
    max_steps = next(t.max_steps for t in env.tasks() if t.task_id == "pick_color")
    assert not st.success and st.subtasks_done == 0 and st.steps == max_steps and st.done
    assert st.info.failure_cause is None  # not ended early: the worker records a timeout
    with pytest.raises(RuntimeError, match="after the episode is done"):
        env.step(np.zeros(7))


def test_blind_policy_fails_pick_color_most_of_the_time(env) -> None:
    """A policy that ignores the image (so the cube positions) goes to the middle of the
    placement area and tries to pick there: it should rarely succeed."""
    from workers.experts.tabletop import expert_action

    def blind(priv):
        fake = dict(priv)
        pos = np.array(priv["cube_pos"], dtype=float)
        pos[priv["targets"][0], :2] = [0.0, -0.065]  # where a blind policy would guess
        fake["cube_pos"] = pos
        fake["grasped"] = [False] * len(pos)
        return expert_action(fake)

    wins = sum(_run(env, "pick_color", 200 + i, blind).success for i in range(8))
    assert wins <= 1


def test_instructions_name_colors_and_vary(env) -> None:
    texts = set()
    for i in range(6):
        texts.add(env.reset("pick_color", i, 0).status.instruction)
    assert (
        all(t.startswith("pick up the ") and t.endswith(" cube") for t in texts) and len(texts) >= 2
    )
    text = env.reset("organize", 0, 0).status.instruction
    assert text.startswith("put the ") and text.count(",") >= 3


def test_images_render_only_when_read(env) -> None:
    obs = env.reset("pick_color", 0, 0)
    for _ in range(3):
        obs = env.step(np.zeros(7))
    assert obs.images.rendered == ()
    img = obs.images["wrist"]
    assert img.shape == (64, 64, 3) and img.dtype == np.uint8 and obs.images.rendered == ("wrist",)
    assert obs.state.shape == (8,)
    assert not obs.privileged.computed  # only experts read it; nobody paid for it here
    old = obs
    obs = env.step(np.zeros(7))
    assert old.images["wrist"] is img  # rendered before the step: still served
    with pytest.raises(RuntimeError, match="stepped past"):
        old.images["agentview"]  # would show the new moment: refused
    with pytest.raises(RuntimeError, match="stepped past"):
        old.privileged["cube_pos"]
    assert obs.privileged["cube_pos"].shape == (3, 3) and obs.privileged.computed


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"image_size": 0}, r"env.params.image_size=0 must be > 0"),
        (
            {"cameras": ["top"]},
            r"env.params.cameras=\['top'\]: choose one or more of \['agentview', 'wrist'\]",
        ),
        ({"max_steps": {"fly": 3}}, r"env.params.max_steps=\{'fly': 3\}"),
        ({"state_dims": [0, 8]}, r"env.params.state_dims=\[0, 8\]: distinct dims of the 8-d"),
        ({"state_dims": [1, 1]}, r"env.params.state_dims=\[1, 1\]"),
    ],
)
def test_bad_params(kwargs, pattern) -> None:
    from workers.envs.suites.tabletop.env import TabletopEnv

    with pytest.raises(ValueError, match=pattern):
        TabletopEnv(**kwargs)


def test_unknown_task_lists_valid_ones(env) -> None:
    with pytest.raises(
        ValueError,
        match=r"'fly' is not a tabletop task; valid: \['pick_color', 'stack_color', 'organize'\]",
    ):
        env.reset("fly", 0, 0)


def test_an_episode_does_not_depend_on_the_one_before(env) -> None:
    """Paired cells and resumed runs rely on (task, episode, seed) fixing the whole trajectory,
    whichever episode an actor ran before on the same scene (robosuite's gripper keeps its
    integrated command across soft resets unless the scene clears it)."""
    from workers.envs.suites.tabletop.env import TabletopEnv

    def roll(e, episode: int, gripper: float) -> np.ndarray:
        e.reset("pick_color", episode, 0)
        states = []
        for t in range(30):
            obs = e.step(np.array([0.3, -0.2, -0.5, 0, 0, 0, gripper if t < 20 else -1.0]))
            states.append(obs.state)
        return np.array(states)

    roll(env, 4, gripper=1.0)  # ends with the gripper command wound up by the close
    after = roll(env, 7, gripper=-1.0)
    fresh_env = TabletopEnv(image_size=32, cameras=("agentview",))
    try:
        fresh = roll(fresh_env, 7, gripper=-1.0)
    finally:
        fresh_env.close()
    np.testing.assert_array_equal(after, fresh)


def test_state_dims_leave_out_the_orientation(env) -> None:
    """``state_dims`` gives a policy some of the 8 dims (the zoo's lerobot architectures get
    position and gripper, training/zoo_state.py); the same episode, the same values."""
    from workers.envs.suites.tabletop.env import TabletopEnv

    cut = TabletopEnv(state_dims=[0, 1, 2, 6, 7])
    full, part = env.reset("pick_color", 3, 0), cut.reset("pick_color", 3, 0)
    assert part.state.shape == (5,) and cut.state_dim == 5
    np.testing.assert_array_equal(part.state, full.state[[0, 1, 2, 6, 7]])
    assert TabletopEnv.describe(state_dims=[0, 1, 2, 6, 7]).state_dim == 5
    assert TabletopEnv.describe().state_dim == 8
    cut.close()
