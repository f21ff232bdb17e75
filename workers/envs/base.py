"""What an environment is to the pipeline, and the contract checker every adapter must pass.

An env holds one simulated scene at a time. ``reset(task_id, episode_index, seed)`` puts it in
the task's deterministic initial state for that episode (so every IDR cell of a grid sees the
same scenes), ``step(action)`` advances one control step. Status is read from properties:
``success``, ``done``, ``subtasks_done`` (for chains, CALVIN-style), ``instruction``.

Observations are what the env renders, before any policy convention: camera images as uint8
(H, W, 3) arrays and the proprioceptive state as a float32 vector.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np


@dataclass(frozen=True)
class TaskSpec:
    """One task of a suite."""

    task_id: str  # stable id used in keys and file names
    name: str  # human-readable name
    max_steps: int  # control steps before the episode ends as a failure (protocol constant)
    subtasks_total: int = 1  # > 1 for chains: episode stops at the first failed subtask
    suite: str | None = None  # benchmark suite of this task when an env spans several (LIBERO)
    instruction: str | None = None  # fixed instruction, when known without a simulator
    episodes_total: int | None = None  # a fixed list of episodes (CALVIN, SIMPLER); None: any
    perturbation: str | None = None  # the kind applied to this task (its id names it too)
    severity: float | None = None  # the kind's severity, in its unit


class LazyImages(Mapping[str, np.ndarray]):
    """Camera images rendered on first access, per camera, then cached.

    An env returns these so that steps executed open-loop from an action chunk (nobody reads
    the images) and cameras a backbone does not use cost no rendering. An env that renders the
    live simulator passes ``is_current``: once it has stepped on, an image not yet rendered
    cannot show this observation's moment any more, and reading it raises instead."""

    def __init__(
        self,
        cameras: tuple[str, ...],
        render_one: Callable[[str], np.ndarray],
        is_current: Callable[[], bool] | None = None,
    ) -> None:
        self._cameras = tuple(cameras)
        self._render_one = render_one
        self._is_current = is_current
        self._images: dict[str, np.ndarray] = {}

    def __getitem__(self, key: str) -> np.ndarray:
        if key not in self._cameras:
            raise KeyError(key)
        if key not in self._images:
            _require_current(self._is_current, f"image {key!r}")
            self._images[key] = self._render_one(key)
        return self._images[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._cameras)

    def __len__(self) -> int:
        return len(self._cameras)

    @property
    def rendered(self) -> tuple[str, ...]:
        return tuple(self._images)


def _require_current(is_current: Callable[[], bool] | None, what: str) -> None:
    if is_current is not None and not is_current():
        raise RuntimeError(
            f"{what} of an observation the env has stepped past: read it before stepping"
        )


class LazyState(Mapping[str, Any]):
    """A dict computed on first access (the privileged simulator state only experts read),
    with the same staleness rule as LazyImages."""

    def __init__(
        self, compute: Callable[[], dict[str, Any]], is_current: Callable[[], bool] | None = None
    ) -> None:
        self._compute = compute
        self._is_current = is_current
        self._data: dict[str, Any] | None = None

    def _get(self) -> dict[str, Any]:
        if self._data is None:
            _require_current(self._is_current, "privileged state")
            self._data = self._compute()
        return self._data

    def __getitem__(self, key: str) -> Any:
        return self._get()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self._get())

    def __len__(self) -> int:
        return len(self._get())

    @property
    def computed(self) -> bool:
        return self._data is not None


@dataclass
class EnvObservation:
    images: Mapping[str, np.ndarray]  # camera name -> uint8 (H, W, 3), maybe LazyImages
    state: np.ndarray  # float32 (S,)
    privileged: Mapping[str, Any] | None = None  # simulator state for scripted experts only


# Members an env may have beyond the Env protocol, with the default the pipeline assumes when
# it has not: read them with env_member(), never with a getattr of one's own, so that every
# reader agrees and check_env() checks them.
OPTIONAL_ENV_MEMBERS: dict[str, tuple[Any, str]] = {
    "gripper_index": (
        None,
        "int: the action dim that commands the gripper (gripper events in the report); "
        "None: the env has no gripper",
    ),
    "init_state_id": (
        None,
        "str, after reset: which initial state the episode started from (LIBERO's fixed "
        "init states, the tabletop's seeded layout); None: '<seed>/<episode_index>'",
    ),
    "failure_cause": (
        None,
        "str | None, once done: a code for why the env ended a failed episode early "
        "(e.g. 'wrong_order'); None: it did not (the step budget ran out: 'timeout')",
    ),
    "failure_reason": (None, "str | None: the env's words for failure_cause"),
    "suite_tasks": (
        None,
        "classmethod(**params) -> list[TaskSpec]: the tasks without starting a simulator "
        "(pre-flight before any actor); None: the env is built once to call tasks()",
    ),
    "render_backend": (
        None,
        "str: the renderer of an env that does not render with MuJoCo's headless GL (e.g. "
        "PyBullet's CPU renderer 'pybullet-tiny'), recorded with every episode; None: the "
        "worker's MuJoCo backend (egl / osmesa)",
    ),
    "policy_reset_per_subtask": (
        False,
        "bool: each subtask of a chain is a rollout of its own (CALVIN): when one is done the "
        "policy is reset, the rest of its chunk dropped and the instruction read anew",
    ),
    "check_runtime": (
        None,
        "classmethod(**params) -> None: check what the env needs in the interpreter it runs in "
        "(simulator packages, a checkout), raising ValueError naming the field and the fix; "
        "the pre-flight calls it there (in an env server for env.python) before any episode",
    ),
    "describe": (
        None,
        "classmethod(**params) -> workers.io_spec.EnvIO: cameras, image size, state and "
        "action dims and protocol, without a simulator (the pre-flight matches a checkpoint "
        "against them); None: no check",
    ),
    "check_tasks": (
        None,
        "classmethod(task_ids, episodes, **params) -> None: check, on the driver before any "
        "episode, what the selected tasks' first ``episodes`` episodes need (SIMPLER: their "
        "assets), raising ValueError naming the fix",
    ),
    "perturbation_kinds": (
        (),
        "tuple[str, ...]: the scene perturbations the env applies (workers/envs/wrappers/perturbations.py; "
        "image kinds need nothing of the env)",
    ),
    "set_perturbation": (
        None,
        "method(Perturbation | None): the scene perturbation of the next reset (None: the "
        "unperturbed scene, to the bit); with perturbation_kinds",
    ),
}


def checked_action(action: Any, action_dim: int, started: bool, done: bool) -> np.ndarray:
    """``action`` as float64 (action_dim,), or the error the Env protocol's ``step`` raises:
    ValueError for a wrong shape or a NaN / inf, RuntimeError before reset or after done."""
    a = np.asarray(action, dtype=np.float64)
    if a.shape != (action_dim,):
        raise ValueError(f"action must have shape ({action_dim},), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"action has NaN or inf: {a.tolist()}")
    if not started:
        raise RuntimeError("step() before reset()")
    if done:
        raise RuntimeError("step() after the episode is done; call reset()")
    return a


def env_member(env: Any, name: str) -> Any:
    """An optional member of ``env`` (see OPTIONAL_ENV_MEMBERS), or its documented default."""
    default, _ = OPTIONAL_ENV_MEMBERS[name]
    return getattr(env, name, default)


@runtime_checkable
class Env(Protocol):
    """The members every env has. It may also have those of OPTIONAL_ENV_MEMBERS."""

    suite: str
    control_hz: float  # control steps per simulated second
    action_dim: int
    state_dim: int
    cameras: tuple[str, ...]

    def tasks(self) -> list[TaskSpec]: ...

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation: ...

    def step(self, action: np.ndarray) -> EnvObservation:
        """Apply one (action_dim,) action; raise ValueError for a wrong shape, RuntimeError
        after the episode is done."""

    @property
    def task(self) -> TaskSpec: ...

    @property
    def instruction(self) -> str: ...

    @property
    def success(self) -> bool: ...

    @property
    def done(self) -> bool: ...

    @property
    def subtasks_done(self) -> int: ...

    @property
    def steps(self) -> int: ...

    def close(self) -> None: ...


class EnvContractError(AssertionError):
    """An env adapter breaks the contract; the message says which rule."""


def _require(cond: bool, msg: str) -> None:
    if not cond:
        raise EnvContractError(msg)


def _check_obs(env: Env, obs: EnvObservation, where: str) -> None:
    _require(isinstance(obs, EnvObservation), f"{where}: must return an EnvObservation")
    _require(bool(obs.images), f"{where}: observation has no camera images")
    _require(
        set(obs.images) == set(env.cameras),
        f"{where}: cameras {sorted(obs.images)} differ from env.cameras {sorted(env.cameras)}",
    )
    for cam, img in obs.images.items():
        _require(
            isinstance(img, np.ndarray)
            and img.dtype == np.uint8
            and img.ndim == 3
            and img.shape[2] == 3,
            f"{where}: image {cam!r} must be uint8 (H, W, 3), got "
            f"{getattr(img, 'dtype', type(img))} {getattr(img, 'shape', '')}",
        )
    s = obs.state
    _require(
        isinstance(s, np.ndarray) and s.ndim == 1 and s.shape[0] == env.state_dim,
        f"{where}: state must be a ({env.state_dim},) array, got {getattr(s, 'shape', type(s))}",
    )
    _require(np.issubdtype(s.dtype, np.floating), f"{where}: state must be float, got {s.dtype}")
    _require(bool(np.isfinite(s).all()), f"{where}: state has NaN or inf")


def _same(a: EnvObservation, b: EnvObservation) -> bool:
    return np.array_equal(a.state, b.state) and all(
        np.array_equal(a.images[c], b.images[c]) for c in a.images
    )


def _check_optional_members(env: Env) -> None:
    """The members of OPTIONAL_ENV_MEMBERS an env has, just after a reset."""
    g = env_member(env, "gripper_index")
    _require(
        g is None or (isinstance(g, int) and 0 <= g < env.action_dim),
        f"gripper_index must be None or an int in [0, action_dim={env.action_dim}), got {g!r}",
    )
    init = env_member(env, "init_state_id")
    _require(
        init is None or (isinstance(init, str) and init != ""),
        f"init_state_id must be None or a non-empty str after reset, got {init!r}",
    )
    _require(
        env_member(env, "failure_cause") is None,
        "after reset: failure_cause must be None (no episode has failed yet)",
    )
    listing = env_member(type(env), "suite_tasks")
    _require(listing is None or callable(listing), "suite_tasks must be a classmethod")
    for name in ("describe", "check_runtime"):
        member = env_member(type(env), name)
        _require(member is None or callable(member), f"{name} must be a classmethod")
    backend = env_member(env, "render_backend")
    _require(
        backend is None or (isinstance(backend, str) and backend != ""),
        f"render_backend must be None or a non-empty str, got {backend!r}",
    )
    _require(
        isinstance(env_member(env, "policy_reset_per_subtask"), bool),
        "policy_reset_per_subtask must be a bool",
    )


def check_env(
    env: Env,
    *,
    task_id: str | None = None,
    seed: int = 0,
    n_steps: int = 5,
    run_to_horizon: bool = False,
) -> None:
    """Check that ``env`` honours the contract; raise EnvContractError naming the broken rule.

    In the spirit of gymnasium's ``check_env``. ``run_to_horizon`` also steps until ``done`` to
    check the max-steps rule (cheap for fakes, minutes for LIBERO).
    """
    _require(isinstance(env, Env), f"{type(env).__name__} does not implement the Env protocol")
    _require(env.control_hz > 0, f"control_hz must be > 0, got {env.control_hz}")
    _require(env.action_dim > 0 and env.state_dim > 0, "action_dim and state_dim must be > 0")
    tasks = env.tasks()
    _require(len(tasks) > 0, "tasks() is empty")
    ids = [t.task_id for t in tasks]
    _require(len(set(ids)) == len(ids), f"task ids are not unique: {ids}")
    for t in tasks:
        _require(t.max_steps > 0, f"task {t.task_id}: max_steps must be > 0")
        _require(t.subtasks_total >= 1, f"task {t.task_id}: subtasks_total must be >= 1")
    task_id = task_id or ids[0]

    obs0 = env.reset(task_id, 0, seed)
    _check_obs(env, obs0, "reset")
    _require(env.task.task_id == task_id, "env.task does not match the task reset to")
    _require(
        isinstance(env.instruction, str) and env.instruction.strip() != "", "instruction is empty"
    )
    _require(env.steps == 0 and not env.done, "after reset: steps must be 0 and done False")
    _require(not env.success and env.subtasks_done == 0, "after reset: no success, no subtask done")

    _check_optional_members(env)

    again = env.reset(task_id, 0, seed)
    _require(_same(obs0, again), "reset(task, episode 0, seed) twice gave different observations")
    other = env.reset(task_id, 1, seed)
    _require(
        not _same(obs0, other), "episodes 0 and 1 start from the same state: init states must vary"
    )

    env.reset(task_id, 0, seed)
    try:
        env.step(np.zeros(env.action_dim + 1, dtype=np.float32))
    except ValueError:
        pass
    else:
        raise EnvContractError("step() with a wrong action shape must raise ValueError")

    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, size=(n_steps, env.action_dim)).astype(np.float32)
    trajectories = []
    for _ in range(2):
        env.reset(task_id, 0, seed)
        traj = []
        for i, a in enumerate(actions):
            if env.done:
                break
            obs = env.step(a)
            _check_obs(env, obs, f"step {i}")
            _require(env.steps == i + 1, f"steps must count control steps: {env.steps} != {i + 1}")
            total = env.task.subtasks_total
            _require(0 <= env.subtasks_done <= total, f"subtasks_done out of [0, {total}]")
            _require(isinstance(env.success, bool | np.bool_), "success must be a bool")
            _require(
                not (env.success and env_member(env, "failure_cause")),
                "failure_cause is set on a successful episode",
            )
            traj.append(obs.state.copy())
        trajectories.append(traj)
    _require(
        all(np.array_equal(a, b) for a, b in zip(*trajectories, strict=True)),
        "same init state and actions gave different trajectories: stepping must be deterministic",
    )

    if run_to_horizon:
        env.reset(task_id, 0, seed)
        limit = env.task.max_steps
        while not env.done:
            env.step(np.zeros(env.action_dim, dtype=np.float32))
            _require(env.steps <= limit, f"done not set after max_steps={limit}")
        try:
            env.step(np.zeros(env.action_dim, dtype=np.float32))
        except RuntimeError:
            pass
        else:
            raise EnvContractError("step() after done must raise RuntimeError")
        cause, reason = env_member(env, "failure_cause"), env_member(env, "failure_reason")
        _require(
            cause is None or isinstance(cause, str),
            f"failure_cause must be a str or None: {cause!r}",
        )
        _require(
            reason is None or isinstance(reason, str),
            f"failure_reason must be a str or None: {reason!r}",
        )
        _require(not (env.success and cause), "failure_cause is set on a successful episode")
