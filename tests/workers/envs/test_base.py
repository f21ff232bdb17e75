"""The env contract checker: the fakes pass it, broken envs fail it with the rule named."""

from __future__ import annotations

import numpy as np
import pytest

from tests.doubles.envs import PropertyMarkerEnv
from workers.envs.checks import EnvContractError, check_env
from workers.envs.fakes import FakeMarkerEnv


@pytest.mark.parametrize("env_cls", [FakeMarkerEnv, PropertyMarkerEnv])
def test_fake_marker_env_passes_contract(env_cls) -> None:
    """The status as a record, and (a user's env written before it) as properties."""
    env = env_cls()
    for task in env.tasks():
        check_env(env, task_id=task.task_id, run_to_horizon=True)


def test_a_property_env_reads_as_the_same_records_as_the_record_env() -> None:
    """The adapter: a user's env that keeps status as properties gives, step for step, the
    record the env that returns it gives."""
    from workers.envs.base import episode_status

    a, b = FakeMarkerEnv(), PropertyMarkerEnv()
    for task in ("reach", "reach_chain"):
        oa, ob = a.reset(task, 3, 0), b.reset(task, 3, 0)
        assert ob.status is None
        while True:
            assert oa.status == episode_status(b, ob)
            if oa.status.done:
                break
            act = np.array([0.7, -0.4])
            oa, ob = a.step(act), b.step(act)


def test_the_clock_counts_steps_and_guards_the_call_order() -> None:
    from workers.envs.base import TaskSpec
    from workers.envs.episode_clock import EpisodeClock

    clock = EpisodeClock(2)
    with pytest.raises(RuntimeError, match="before reset"):
        clock.take([0.0, 0.0])
    clock.start(TaskSpec("t", "t", max_steps=2))
    with pytest.raises(ValueError, match="shape"):
        clock.take([0.0])
    with pytest.raises(ValueError, match="NaN"):
        clock.take([np.nan, 0.0])
    assert clock.steps == 0  # refused actions are not counted
    clock.take([0.0, 1.0])
    assert not clock.status("go", False).done
    clock.take(np.ones(2))
    st = clock.status("go", False)
    assert st.done and st.steps == 2 and st.subtasks_done == 0  # the horizon
    with pytest.raises(RuntimeError, match="after the episode is done"):
        clock.take([0.0, 0.0])
    clock.start(TaskSpec("t", "t", max_steps=5))
    clock.take([0.0, 0.0])
    st = clock.status("go", True, ended=True)
    assert st.done and st.success and st.subtasks_done == 1  # the suite ended it


def test_the_status_record_crosses_the_wire_unchanged() -> None:
    from workers.envs.base import EpisodeStatus

    st = FakeMarkerEnv().reset("reach_chain", 0, 0).status
    assert EpisodeStatus.from_wire(st.to_wire()) == st


class _SameInitEnv(FakeMarkerEnv):
    def reset(self, task_id, episode_index, seed):
        return super().reset(task_id, 0, seed)


class _NondeterministicEnv(FakeMarkerEnv):
    _rng = np.random.default_rng()

    def step(self, action):
        return super().step(action + self._rng.normal(scale=0.1, size=2))


class _LaxShapeEnv(FakeMarkerEnv):
    def step(self, action):
        return super().step(np.asarray(action)[:2])


class _FloatImageEnv(FakeMarkerEnv):
    def _observe(self):
        obs = super()._observe()
        obs.images = {k: v.astype(np.float32) for k, v in obs.images.items()}
        return obs


class _NeverDoneEnv(PropertyMarkerEnv):
    @property
    def done(self):
        return False


class _GripperOutOfRangeEnv(FakeMarkerEnv):
    gripper_index = 2  # the action has 2 dims


class _EmptyInitStateEnv(PropertyMarkerEnv):
    init_state_id = ""


class _StaleFailureCauseEnv(PropertyMarkerEnv):
    failure_cause = "wrong_order"  # set before any episode failed


class _NoInstructionEnv(PropertyMarkerEnv):
    @property
    def instruction(self) -> str:
        return ""


class _SaysItDescribesNoTaskEnv(_NoInstructionEnv):
    empty_instruction_ok = True  # as the lerobot suite on PushT: lerobot-eval feeds ""


class _FailureOnSuccessEnv(PropertyMarkerEnv):
    @property
    def success(self) -> bool:
        return self._steps >= 1

    @property
    def failure_cause(self) -> str | None:
        return "wrong_order" if self.success else None


@pytest.mark.parametrize(
    ("env_cls", "rule"),
    [
        (_GripperOutOfRangeEnv, "gripper_index must be None or an int in"),
        (_EmptyInitStateEnv, "init_state_id must be None or a non-empty str"),
        (_StaleFailureCauseEnv, "after reset: failure_cause must be None"),
        (_FailureOnSuccessEnv, "failure_cause is set on a successful episode"),
        (_NoInstructionEnv, "instruction is empty"),
        (_SameInitEnv, "init states must vary"),
        (_NondeterministicEnv, "stepping must be deterministic"),
        (_LaxShapeEnv, "wrong action shape must raise ValueError"),
        (_FloatImageEnv, "must be uint8"),
        (_NeverDoneEnv, "done not set after max_steps"),
    ],
)
def test_broken_envs_fail_with_the_rule_named(env_cls, rule) -> None:
    with pytest.raises(EnvContractError, match=rule):
        check_env(env_cls(), run_to_horizon=True)


def test_an_env_that_describes_no_task_may_say_so_and_give_an_empty_instruction() -> None:
    check_env(_SaysItDescribesNoTaskEnv(), run_to_horizon=True)


def test_image_carries_information_the_state_lacks() -> None:
    """Blind policies fail: the target is in the image only, and varies per episode."""
    env = FakeMarkerEnv()
    states, images = [], []
    for i in range(5):
        obs = env.reset("reach", i, seed=0)
        states.append(obs.state)
        images.append(obs.images["agentview"][..., 0])
    assert len({img.tobytes() for img in images}) == 5
    assert all(s.shape == (2,) for s in states)


def test_success_requires_reaching_the_marker() -> None:
    env = FakeMarkerEnv()
    st = env.reset("reach", 0, seed=0).status
    target, pos = env._targets[0], env._pos
    while not st.done:
        st = env.step(np.clip((target - env._pos) / 0.1, -1, 1)).status
    assert st.success and st.subtasks_done == 1 and st.steps < env.tasks()[0].max_steps
    assert np.linalg.norm(pos - target) > 0.08


def test_optional_members_have_one_documented_default() -> None:
    """What the pipeline assumes for an env or backbone that lacks an optional member."""
    from dataclasses import fields

    from workers.backbones.base import OPTIONAL_BACKBONE_MEMBERS, backbone_member
    from workers.envs.base import (
        EpisodeInfo,
        SuiteHooks,
        SuiteInfo,
        _read,
        suite_hooks,
        suite_info,
    )

    bare = object()
    for group, read in (
        (SuiteInfo, suite_info),
        (SuiteHooks, suite_hooks),
        (EpisodeInfo, lambda env: _read(env, EpisodeInfo)),
    ):
        got = read(bare)
        for f in fields(group):
            assert getattr(got, f.name) is f.default and f.metadata["doc"]
    for name, (default, doc) in OPTIONAL_BACKBONE_MEMBERS.items():
        assert backbone_member(bare, name) is default and doc
    assert suite_info(_GripperOutOfRangeEnv()).gripper_index == 2
    with pytest.raises(AttributeError):
        _ = suite_info(bare).gripper  # type: ignore[attr-defined]  # a typo, not a silent default


def test_a_member_only_a_built_env_knows_reads_as_its_default_off_the_class() -> None:
    """A property (SIMPLER's render_backend) is a value of an env, not of its class."""
    from workers.envs.base import suite_hooks, suite_info

    class _PropertyEnv(FakeMarkerEnv):
        @property
        def render_backend(self) -> str:
            return "sapien-vulkan-gpu/ibl"

    assert suite_info(_PropertyEnv).render_backend is None
    assert suite_info(_PropertyEnv()).render_backend == "sapien-vulkan-gpu/ibl"
    assert suite_info(FakeMarkerEnv).action_dim == 2
    assert suite_hooks(FakeMarkerEnv).suite_tasks is not None
    assert suite_hooks(FakeMarkerEnv).check_runtime is None
