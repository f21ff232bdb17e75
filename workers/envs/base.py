"""What an environment is to the pipeline (the contract checker every adapter must pass is
``workers.envs.checks.check_env``).

An env holds one simulated scene at a time. ``reset(task_id, episode_index, seed)`` puts it in
the task's deterministic initial state for that episode (so every IDR cell of a grid sees the
same scenes), ``step(action)`` advances one control step. Both return an :class:`EnvObservation`
whose ``status`` is a frozen :class:`EpisodeStatus`: task id, instruction, steps, success, done,
subtasks done (chains, CALVIN-style) and the episode's :class:`EpisodeInfo`, as Gymnasium's
``step`` returns its status with the observation. Suites count steps and guard the call order
with one helper, ``workers.envs.episode_clock.EpisodeClock``. A user's env that keeps status
as properties (``task``, ``instruction``, ``success``, ``done``, ``subtasks_done``, ``steps``)
works unchanged: :func:`episode_status` reads them into the record.

Observations are what the env renders, before any policy convention: camera images as uint8
(H, W, 3) arrays and the proprioceptive state as a float32 vector.

Beyond the ``Env`` protocol an env may have optional members, in three groups (as Gymnasium
keeps an env's ``metadata`` apart from the ``info`` its reset and step return). Each group is a
frozen dataclass read through one accessor (the episode's group comes with its status), which fills in the documented default of a member
the env lacks (never read them with a getattr of one's own: every reader agrees, and
``check_env`` checks what the accessors return):

- ``suite_info(env_or_cls) -> SuiteInfo``: static metadata of the suite (``gripper_index``,
  ``render_backend``, ``policy_reset_per_subtask``, ``perturbation_kinds``,
  ``server_setup_hint``, the class's ``action_dim``, ``renders_hidden_objects``); off a class,
  a member only a built env knows (a property) reads as its default;
- ``suite_hooks(env_or_cls) -> SuiteHooks``: what the suite can do without an episode,
  callables or None (``suite_tasks``, ``check_runtime``, ``describe``, ``check_tasks``: class
  methods the driver's pre-flight calls; ``set_perturbation``: the env's, before a reset);
- ``EpisodeInfo`` (``EpisodeStatus.info``): what the current episode started from and, once
  done, ended with (``init_state_id``, ``failure_cause``, ``failure_reason``).

Each field's default and documentation: ``dataclasses.fields(SuiteInfo)`` (``metadata["doc"]``).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field, fields
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


# -- what an env may have beyond the Env protocol (see the module docstring) ----------------------
# Each field's default is what the pipeline assumes of an env without the member; its doc is
# kept with it (``dataclasses.fields(SuiteInfo)[i].metadata["doc"]``).


@dataclass(frozen=True)
class SuiteInfo:
    """What a suite is, beyond the Env protocol: constants of the env class, or of the built env
    (``render_backend`` may depend on its params). Read with :func:`suite_info`."""

    gripper_index: int | None = field(
        default=None,
        metadata={
            "doc": "int: the action dim that commands the gripper (gripper events in the "
            "report); None: the env has no gripper"
        },
    )
    render_backend: str | None = field(
        default=None,
        metadata={
            "doc": "str: the renderer of an env that does not render with MuJoCo's headless GL "
            "(e.g. PyBullet's CPU renderer 'pybullet-tiny'), recorded with every episode; "
            "None: the worker's MuJoCo backend (egl / osmesa)"
        },
    )
    empty_instruction_ok: bool = field(
        default=False,
        metadata={
            "doc": "bool: the env describes no task and gives an empty instruction, as "
            "lerobot-eval feeds its policies on such envs (PushT, ALOHA); False: an empty "
            "instruction breaks the contract"
        },
    )
    policy_reset_per_subtask: bool = field(
        default=False,
        metadata={
            "doc": "bool: each subtask of a chain is a rollout of its own (CALVIN): when one is "
            "done the policy is reset, the rest of its chunk dropped and the instruction read anew"
        },
    )
    perturbation_kinds: tuple[str, ...] = field(
        default=(),
        metadata={
            "doc": "tuple[str, ...]: the scene perturbations the env applies (with "
            "SuiteHooks.set_perturbation; workers/envs/wrappers/perturbations.py; image kinds "
            "need nothing of the env)"
        },
    )
    server_setup_hint: str | None = field(
        default=None,
        metadata={
            "doc": "str: how to make the interpreter an env server of this suite runs in "
            "(env.python), said when the pre-flight refuses a missing one; None: nothing to say"
        },
    )
    action_dim: int | None = field(
        default=None,
        metadata={
            "doc": "int: the Env protocol's action dim, where the class declares it (the "
            "pre-flight checks a checkpoint against it before any env is built); None: known "
            "only once built"
        },
    )
    renders_hidden_objects: bool = field(
        default=False,
        metadata={
            "doc": "bool: the env has ``object_hidden_images() -> dict[str, np.ndarray]``, the "
            "current state from the observation's cameras (same size, dtype and look as its "
            "images) with the instruction's objects hidden and nothing else changed, the "
            "simulation untouched (Policy Contrastive Decoding's object-removed image; the "
            "tabletop); False: it has none"
        },
    )


@dataclass(frozen=True)
class SuiteHooks:
    """What a suite can do without an episode: class-level callables (``None``: the suite
    cannot, and the pipeline does without). Read with :func:`suite_hooks`."""

    suite_tasks: Callable[..., list[TaskSpec]] | None = field(
        default=None,
        metadata={
            "doc": "classmethod(**params) -> list[TaskSpec]: the tasks without starting a "
            "simulator (pre-flight before any actor); None: the env is built once to call tasks()"
        },
    )
    check_runtime: Callable[..., None] | None = field(
        default=None,
        metadata={
            "doc": "classmethod(**params) -> None: check what the env needs in the interpreter "
            "it runs in (simulator packages, a checkout), raising ValueError naming the field "
            "and the fix; the pre-flight calls it there (in an env server for env.python) "
            "before any episode"
        },
    )
    describe: Callable[..., Any] | None = field(
        default=None,
        metadata={
            "doc": "classmethod(**params) -> workers.io_spec.EnvIO: cameras, image size, state "
            "and action dims and protocol, without a simulator (the pre-flight matches a "
            "checkpoint against them); None: no check"
        },
    )
    check_tasks: Callable[..., None] | None = field(
        default=None,
        metadata={
            "doc": "classmethod(task_ids, episodes, **params) -> None: check, on the driver "
            "before any episode, what the selected tasks' first ``episodes`` episodes need "
            "(SIMPLER: their assets), raising ValueError naming the fix"
        },
    )
    set_perturbation: Callable[[Any], None] | None = field(
        default=None,
        metadata={
            "doc": "method(Perturbation | None): the scene perturbation of the next reset "
            "(None: the unperturbed scene, to the bit); with SuiteInfo.perturbation_kinds"
        },
    )


@dataclass(frozen=True)
class EpisodeInfo:
    """What the env's current episode started from and, once done, ended with. Read with
    ``EpisodeStatus.info`` (:func:`episode_status`)."""

    init_state_id: str | None = field(
        default=None,
        metadata={
            "doc": "str, after reset: which initial state the episode started from (LIBERO's "
            "fixed init states, the tabletop's seeded layout); None: '<seed>/<episode_index>'"
        },
    )
    failure_cause: str | None = field(
        default=None,
        metadata={
            "doc": "str | None, once done: a code for why the env ended a failed episode early "
            "(e.g. 'wrong_order'); None: it did not (the step budget ran out: 'timeout')"
        },
    )
    failure_reason: str | None = field(
        default=None, metadata={"doc": "str | None: the env's words for failure_cause"}
    )


@dataclass(frozen=True)
class EpisodeStatus:
    """The episode after a reset or a step, as the env returns it (``EnvObservation.status``)."""

    task_id: str
    instruction: str  # the current one (CALVIN: the current subtask's)
    steps: int  # control steps since the reset
    success: bool
    done: bool  # the episode is over: step() now raises
    subtasks_done: int = 0  # chains; a one-step task: int(success)
    info: EpisodeInfo = EpisodeInfo()

    def to_wire(self) -> dict[str, Any]:
        """A flat dict of plain values (the env server's reply)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "info"}
        return {**out, **{f.name: getattr(self.info, f.name) for f in fields(EpisodeInfo)}}

    @classmethod
    def from_wire(cls, d: Mapping[str, Any]) -> EpisodeStatus:
        info = EpisodeInfo(**{f.name: d.get(f.name) for f in fields(EpisodeInfo)})
        return cls(
            task_id=str(d["task_id"]),
            instruction=str(d["instruction"]),
            steps=int(d["steps"]),
            success=bool(d["success"]),
            done=bool(d["done"]),
            subtasks_done=int(d["subtasks_done"]),
            info=info,
        )


@dataclass
class EnvObservation:
    images: Mapping[str, np.ndarray]  # camera name -> uint8 (H, W, 3), maybe LazyImages
    state: np.ndarray  # float32 (S,)
    privileged: Mapping[str, Any] | None = None  # simulator state for scripted experts only
    # the episode's status (None only from an env that keeps it as properties: episode_status)
    status: EpisodeStatus | None = None


def _read(obj: Any, group: type) -> Any:
    """``group`` with the members ``obj`` has, the defaults for the others. Read off a class, a
    member that only an instance knows (a property) reads as its default."""
    on_class = isinstance(obj, type)
    values = {}
    for f in fields(group):
        value = getattr(obj, f.name, f.default)
        values[f.name] = f.default if on_class and inspect.isdatadescriptor(value) else value
    return group(**values)


def suite_info(env_or_cls: Any) -> SuiteInfo:
    """The suite's metadata, of an env or of its class (see SuiteInfo)."""
    return _read(env_or_cls, SuiteInfo)


def suite_hooks(env_or_cls: Any) -> SuiteHooks:
    """The suite's hooks, of its class (classmethods) or of an env (see SuiteHooks)."""
    return _read(env_or_cls, SuiteHooks)


def episode_status(env: Any, obs: EnvObservation) -> EpisodeStatus:
    """The status ``obs`` carries; for an env that keeps status as properties (a user's env
    written before the record), the record read from them (the adapter)."""
    if obs.status is not None:
        return obs.status
    return EpisodeStatus(
        task_id=env.task.task_id,
        instruction=env.instruction,
        steps=int(env.steps),
        success=bool(env.success),
        done=bool(env.done),
        subtasks_done=int(env.subtasks_done),
        info=_read(env, EpisodeInfo),
    )


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


@runtime_checkable
class Env(Protocol):
    """The members every env has. It may also have those of SuiteInfo and SuiteHooks (read
    them with suite_info and suite_hooks)."""

    suite: str
    control_hz: float  # control steps per simulated second
    action_dim: int
    state_dim: int
    cameras: tuple[str, ...]

    def tasks(self) -> list[TaskSpec]: ...

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        """The task's initial state for this episode; ``status`` set (steps 0, not done)."""

    def step(self, action: np.ndarray) -> EnvObservation:
        """Apply one (action_dim,) action; raise ValueError for a wrong shape, RuntimeError
        before reset or after the episode is done; ``status`` set."""

    def close(self) -> None: ...
