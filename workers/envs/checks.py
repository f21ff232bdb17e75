"""The contract checker every env adapter must pass, in the spirit of Gymnasium's ``check_env``.

:func:`check_env` runs the checks below in order; each checks one property of the ``Env``
protocol (``workers.envs.base``) and raises :class:`EnvContractError` naming the broken rule.
"""

from __future__ import annotations

import numpy as np

from workers.envs.base import (
    Env,
    EnvObservation,
    EpisodeInfo,
    EpisodeStatus,
    SuiteHooks,
    TaskSpec,
    episode_status,
    suite_hooks,
    suite_info,
)


class EnvContractError(AssertionError):
    """An env adapter breaks the contract; the message says which rule."""


def _require(cond: bool, msg: str) -> None:
    if not cond:
        raise EnvContractError(msg)


def check_env(
    env: Env,
    *,
    task_id: str | None = None,
    seed: int = 0,
    n_steps: int = 5,
    run_to_horizon: bool = False,
) -> None:
    """Check that ``env`` honours the contract; raise EnvContractError naming the broken rule.

    ``run_to_horizon`` also steps until ``done`` to check the max-steps rule (cheap for fakes,
    minutes for LIBERO).
    """
    check_constants(env)
    ids = [t.task_id for t in check_task_list(env.tasks())]
    task_id = task_id or ids[0]
    obs0 = env.reset(task_id, 0, seed)
    check_status_after_reset(env, obs0, task_id)
    check_optional_members(env, obs0)
    check_reset_is_deterministic(env, obs0, task_id, seed)
    check_wrong_action_shape_refused(env, task_id, seed)
    check_stepping(env, task_id, seed, n_steps)
    if run_to_horizon:
        check_horizon(env, task_id, seed)


def check_constants(env: Env) -> None:
    """The protocol's members, control rate and dims."""
    _require(isinstance(env, Env), f"{type(env).__name__} does not implement the Env protocol")
    _require(env.control_hz > 0, f"control_hz must be > 0, got {env.control_hz}")
    _require(env.action_dim > 0 and env.state_dim > 0, "action_dim and state_dim must be > 0")


def check_task_list(tasks: list[TaskSpec]) -> list[TaskSpec]:
    """A non-empty task list, unique ids, positive budgets; the tasks."""
    _require(len(tasks) > 0, "tasks() is empty")
    ids = [t.task_id for t in tasks]
    _require(len(set(ids)) == len(ids), f"task ids are not unique: {ids}")
    for t in tasks:
        _require(t.max_steps > 0, f"task {t.task_id}: max_steps must be > 0")
        _require(t.subtasks_total >= 1, f"task {t.task_id}: subtasks_total must be >= 1")
    return tasks


def check_observation(env: Env, obs: EnvObservation, where: str) -> None:
    """Every camera's image uint8 (H, W, 3); a finite float state of ``state_dim``."""
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


def _status(env: Env, obs: EnvObservation, where: str) -> EpisodeStatus:
    """The observation's status record (read from properties for an env that keeps them)."""
    try:
        st = episode_status(env, obs)
    except AttributeError as exc:
        raise EnvContractError(
            f"{where}: the observation has no status (EnvObservation.status) and the env no "
            f"status properties ({exc})"
        ) from None
    _require(isinstance(st, EpisodeStatus), f"{where}: status must be an EpisodeStatus")
    return st


def check_status_after_reset(env: Env, obs: EnvObservation, task_id: str) -> None:
    """The reset's observation, the task reset to, an instruction, a fresh episode."""
    check_observation(env, obs, "reset")
    st = _status(env, obs, "reset")
    _require(st.task_id == task_id, "status.task_id does not match the task reset to")
    _require(
        isinstance(st.instruction, str)
        and (st.instruction.strip() != "" or suite_info(env).empty_instruction_ok),
        "instruction is empty (an env that describes no task, where lerobot-eval feeds '', "
        "says so: empty_instruction_ok = True)",
    )
    _require(st.steps == 0 and not st.done, "after reset: steps must be 0 and done False")
    _require(not st.success and st.subtasks_done == 0, "after reset: no success, no subtask done")


def check_optional_members(env: Env, obs: EnvObservation) -> None:
    """The optional members an env has (base.SuiteInfo, SuiteHooks) and the episode's info,
    just after a reset."""
    info = suite_info(env)
    g = info.gripper_index
    _require(
        g is None or (isinstance(g, int) and 0 <= g < env.action_dim),
        f"gripper_index must be None or an int in [0, action_dim={env.action_dim}), got {g!r}",
    )
    check_episode_info_after_reset(_status(env, obs, "reset").info)
    check_hooks(suite_hooks(type(env)))
    backend = info.render_backend
    _require(
        backend is None or (isinstance(backend, str) and backend != ""),
        f"render_backend must be None or a non-empty str, got {backend!r}",
    )
    _require(
        isinstance(info.policy_reset_per_subtask, bool), "policy_reset_per_subtask must be a bool"
    )
    _require(isinstance(info.renders_hidden_objects, bool), "renders_hidden_objects must be a bool")
    if info.renders_hidden_objects:
        check_object_hidden_images(env, obs)


def check_object_hidden_images(env: Env, obs: EnvObservation) -> None:
    """An env that says ``renders_hidden_objects`` renders, for the current observation, an
    image per camera of it with the same shape and dtype."""
    render = getattr(env, "object_hidden_images", None)
    _require(callable(render), "renders_hidden_objects is True but object_hidden_images is missing")
    hidden = render()
    _require(
        isinstance(hidden, dict) and set(hidden) == set(obs.images),
        f"object_hidden_images: cameras {sorted(hidden) if isinstance(hidden, dict) else hidden!r}"
        f" differ from the observation's {sorted(obs.images)}",
    )
    for cam, img in hidden.items():
        ref = obs.images[cam]
        _require(
            isinstance(img, np.ndarray) and img.dtype == ref.dtype and img.shape == ref.shape,
            f"object_hidden_images: image {cam!r} must be {ref.dtype} {ref.shape} like the "
            f"observation's, got {getattr(img, 'dtype', type(img))} {getattr(img, 'shape', '')}",
        )


def check_episode_info_after_reset(episode: EpisodeInfo) -> None:
    """An init state id, when there is one, says something; no failure before any step."""
    init = episode.init_state_id
    _require(
        init is None or (isinstance(init, str) and init != ""),
        f"init_state_id must be None or a non-empty str after reset, got {init!r}",
    )
    _require(
        episode.failure_cause is None,
        "after reset: failure_cause must be None (no episode has failed yet)",
    )


def check_hooks(hooks: SuiteHooks) -> None:
    """The class's pre-flight hooks, where it has them, are callable."""
    _require(
        hooks.suite_tasks is None or callable(hooks.suite_tasks),
        "suite_tasks must be a classmethod",
    )
    for name in ("describe", "check_runtime"):
        member = getattr(hooks, name)
        _require(member is None or callable(member), f"{name} must be a classmethod")


def check_reset_is_deterministic(env: Env, obs0: EnvObservation, task_id: str, seed: int) -> None:
    """The same episode starts from the same state; the next one from another."""
    again = env.reset(task_id, 0, seed)
    _require(_same(obs0, again), "reset(task, episode 0, seed) twice gave different observations")
    other = env.reset(task_id, 1, seed)
    _require(
        not _same(obs0, other), "episodes 0 and 1 start from the same state: init states must vary"
    )


def _same(a: EnvObservation, b: EnvObservation) -> bool:
    return np.array_equal(a.state, b.state) and all(
        np.array_equal(a.images[c], b.images[c]) for c in a.images
    )


def check_wrong_action_shape_refused(env: Env, task_id: str, seed: int) -> None:
    env.reset(task_id, 0, seed)
    try:
        env.step(np.zeros(env.action_dim + 1, dtype=np.float32))
    except ValueError:
        pass
    else:
        raise EnvContractError("step() with a wrong action shape must raise ValueError")


def check_stepping(env: Env, task_id: str, seed: int, n_steps: int) -> None:
    """``n_steps`` random actions, twice from the same reset: each step's observation and
    status valid, and both trajectories the same."""
    rng = np.random.default_rng(seed)
    actions = rng.uniform(-1, 1, size=(n_steps, env.action_dim)).astype(np.float32)
    trajectories = [_trajectory(env, task_id, seed, actions) for _ in range(2)]
    _require(
        all(np.array_equal(a, b) for a, b in zip(*trajectories, strict=True)),
        "same init state and actions gave different trajectories: stepping must be deterministic",
    )


def _trajectory(env: Env, task_id: str, seed: int, actions: np.ndarray) -> list[np.ndarray]:
    task = _task(env, task_id)
    st = _status(env, env.reset(task_id, 0, seed), "reset")
    traj = []
    for i, a in enumerate(actions):
        if st.done:
            break
        obs = env.step(a)
        check_observation(env, obs, f"step {i}")
        st = _status(env, obs, f"step {i}")
        check_status_after_step(st, task, i + 1)
        traj.append(obs.state.copy())
    return traj


def _task(env: Env, task_id: str) -> TaskSpec:
    return next(t for t in env.tasks() if t.task_id == task_id)


def check_status_after_step(st: EpisodeStatus, task: TaskSpec, steps: int) -> None:
    """Steps counted, subtasks in range, a bool success, no failure cause on a success."""
    _require(st.steps == steps, f"steps must count control steps: {st.steps} != {steps}")
    total = task.subtasks_total
    _require(0 <= st.subtasks_done <= total, f"subtasks_done out of [0, {total}]")
    _require(isinstance(st.success, bool | np.bool_), "success must be a bool")
    _require(
        not (st.success and st.info.failure_cause),
        "failure_cause is set on a successful episode",
    )


def check_horizon(env: Env, task_id: str, seed: int) -> None:
    """Done by max_steps; a step after done refused; the failure cause and reason, str or None."""
    st = _status(env, env.reset(task_id, 0, seed), "reset")
    limit = _task(env, task_id).max_steps
    while not st.done:
        st = _status(env, env.step(np.zeros(env.action_dim, dtype=np.float32)), "step")
        _require(st.steps <= limit, f"done not set after max_steps={limit}")
    try:
        env.step(np.zeros(env.action_dim, dtype=np.float32))
    except RuntimeError:
        pass
    else:
        raise EnvContractError("step() after done must raise RuntimeError")
    cause, reason = st.info.failure_cause, st.info.failure_reason
    _require(
        cause is None or isinstance(cause, str),
        f"failure_cause must be a str or None: {cause!r}",
    )
    _require(
        reason is None or isinstance(reason, str),
        f"failure_reason must be a str or None: {reason!r}",
    )
    _require(not (st.success and cause), "failure_cause is set on a successful episode")
