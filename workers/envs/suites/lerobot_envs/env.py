"""lerobot's env types as a suite: ``env.suite: lerobot`` with ``env.params: {type: pusht, ...}``.

The env is built by lerobot itself: ``make_env_config(type, **config)`` (third-party
``lerobot_env_*`` plugins registered first) and the config's ``create_envs(n_envs=1)``, as
lerobot-eval does, so the scene, its wrappers and its episode length are lerobot's. Each
``(suite, task_id)`` lerobot returns is a task (``pusht``; ``metaworld/3`` for a multi-task
type). The observation is read the way lerobot's ``preprocess_observation`` reads it:
``pixels`` (one image: camera ``image``, policy key ``observation.image``; a dict: one camera
per key, ``observation.images.<key>``) and ``agent_pos`` (``observation.state``). The
instruction is the env's ``task_description`` where it has one, else its ``task``, else
``instruction`` from the config, else the empty string (lerobot-eval's rule: a policy that reads
language gets the same task both ways); success is ``info["is_success"]``; episode ``i`` resets with seed
``seed + i`` (lerobot-eval's rule with one env) and lerobot's new-rollout option; the step
budget is the env's ``_max_episode_steps``, which lerobot-eval's rollout reads (MetaWorld: 500,
whatever the config's ``episode_length`` says), unless ``max_steps`` is given.

``suite: libero`` stays the canonical LIBERO (its protocols and parity are pinned there); a
type whose observation is not pixels and agent_pos (lerobot's LIBERO, RoboCasa...) is refused
naming that.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import sys
from collections.abc import Iterator, Mapping
from typing import Annotated, Any

import numpy as np

from workers.envs.base import EnvObservation, TaskSpec
from workers.envs.episode_clock import EpisodeClock
from workers.envs.gym_env import GymnasiumEnv, env_io
from workers.envs.mujoco.stability import mujoco_instability, raise_if_unstable
from workers.io_spec import EnvIO
from workers.param_doc import Doc
from workers.rendering import own_gl_context, release_gl_context

# the package each env type needs, as lerobot's extras name it (what the refusal says to install)
PACKAGES = {
    "pusht": "gym-pusht (pip install 'lerobot[pusht]'; make setup installs it)",
    "aloha": "gym-aloha (pip install 'lerobot[aloha]'; make setup installs it)",
    "metaworld": "metaworld (pip install 'lerobot[metaworld]'; make setup installs it)",
}
# the types run here, with what was checked (idr-eval list envs shows it; docs/suites/lerobot.md)
RUN_HERE = {
    "pusht": "parity with lerobot-eval tested; conf/pusht_smoke.yaml",
    "metaworld": "parity with lerobot-eval tested; conf/metaworld_smoke.yaml",
    "aloha": "parity with lerobot-eval tested; conf/aloha_smoke.yaml",
}
# types whose observation is lerobot's LIBERO robot_state (read by its LIBERO env processor), not
# agent_pos; refused before lerobot builds them (hf-libero asks on stdin for a dataset folder)
LIBERO_TYPES = {
    "libero": "use env.suite=libero (LIBERO with its openpi and lerobot protocols)",
    "libero_plus": "LIBERO-Plus is not supported; for LIBERO use env.suite=libero",
}


def cfg_package(cfg: Any) -> str:
    """The module a lerobot env config imports to register its env (gym_pusht...)."""
    try:
        return str(cfg.package_name)
    except Exception:  # a config without one
        return f"gym_{cfg.type}"


def known_types() -> list[str]:
    from lerobot.envs.configs import EnvConfig

    _register_plugins()
    return sorted(EnvConfig.get_known_choices())


def _register_plugins() -> None:
    try:
        from lerobot.utils.import_utils import register_third_party_plugins
    except ImportError:  # an older lerobot: no plugins
        return
    register_third_party_plugins()


def env_config(type: str, config: Mapping[str, Any]) -> Any:
    """lerobot's EnvConfig of ``type``, or a ValueError naming the field and the fix."""
    from lerobot.envs.factory import make_env_config

    types = known_types()
    if type not in types:
        close = difflib.get_close_matches(type, types, n=3, cutoff=0.5)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise ValueError(
            f"env.params.type={type!r} is not a lerobot env type{hint}; known: {types}"
        )
    fields = config_fields(type)
    unknown = [k for k in config if k not in fields]
    if unknown:
        from workers.params_model import named_with_hints

        raise ValueError(
            f"env.params (lerobot env type {type!r}): unexpected keyword argument "
            f"{named_with_hints(unknown, fields)}; the suite's own params are type, "
            f"instruction, max_steps and success_key, the others go to lerobot's config: "
            f"{fields}"
        )
    try:
        return make_env_config(type, **config)
    except TypeError as exc:
        raise ValueError(f"env.params (lerobot env type {type!r}): {exc}") from None


def image_option(cfg: Any) -> str | None:
    """The setting of lerobot env config ``cfg`` that makes its env render images (a boolean
    field named for images or pixels, off), as ``env.params.<field>=true``; None if it has
    none."""
    for f in dataclasses.fields(cfg):
        name = f.name.lower()
        if ("image" in name or "pixel" in name) and getattr(cfg, f.name) is False:
            return f"env.params.{f.name}=true"
    return None


def config_fields(type: str) -> list[str]:
    """The fields of lerobot's env config of ``type`` (what ``env.params`` may set beyond the
    suite's own)."""
    import dataclasses

    from lerobot.envs.configs import EnvConfig

    return [f.name for f in dataclasses.fields(EnvConfig.get_choice_class(type))]


class _OneOfVector:
    """A lerobot vector env of one env, seen as a single Gymnasium env (obs unbatched)."""

    def __init__(self, vec: Any, success_key: str = "is_success") -> None:
        self.vec = vec
        self.success_key = success_key
        self.info_keys: list[str] = []  # what the last step's info held (the pre-flight's check)
        self.observation_space = vec.single_observation_space
        self.action_space = vec.single_action_space
        self.spec = None
        self.metadata = dict(getattr(vec, "metadata", {}) or {})

    def reset(self, seed: int) -> tuple[Any, dict]:
        try:  # what lerobot-eval's rollout passes: it thaws an env frozen at its episode's end
            from lerobot.envs.utils import NEW_ROLLOUT_OPTION
        except ImportError:  # an older lerobot
            options = None
        else:
            options = {NEW_ROLLOUT_OPTION: True}
        obs, info = self.vec.reset(seed=[seed], options=options)
        return _unbatch(obs), info

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict]:
        """One step. An episode that ends is reset by the vector env in the same step
        (Gymnasium's SAME_STEP autoreset, as lerobot builds them): its last observation and
        info are then under ``final_obs`` / ``final_info`` (where lerobot-eval reads success),
        and the top-level ones are the next episode's reset."""
        obs, reward, terminated, truncated, info = self.vec.step(action[None])
        ended = bool(terminated[0] or truncated[0])
        final = info.get("final_info") if ended else None
        source = final if isinstance(final, Mapping) else info
        self.info_keys = sorted(k for k in source if not str(k).startswith("_"))  # not masks
        success = source.get(self.success_key)
        out = (
            {self.success_key: bool(np.asarray(success).reshape(-1)[0])}
            if success is not None
            else {}
        )
        last = info.get("final_obs") if ended else None
        obs = last[0] if last is not None else _unbatch(obs)
        return obs, float(reward[0]), bool(terminated[0]), bool(truncated[0]), out

    def call(self, name: str) -> Any:
        try:
            return self.vec.call(name)[0]
        except AttributeError:
            return None

    @property
    def sub_env(self) -> Any | None:
        """The one sub-env, unwrapped (None where the vector env does not expose it)."""
        try:
            return self.vec.envs[0].unwrapped
        except (AttributeError, IndexError):
            return None

    @property
    def unwrapped(self) -> Any | None:
        """The one sub-env, unwrapped, as a Gymnasium wrapper's ``unwrapped`` reads."""
        return self.sub_env

    def attr(self, name: str) -> Any:
        """The sub-env's attribute ``name`` (None where it has none), without calling it."""
        try:
            return self.vec.get_attr(name)[0]
        except AttributeError:
            return None

    def close(self) -> None:
        self.vec.close()


def _task_key(suite: str, tid: Any, name: Any, in_suite: int) -> str:
    """A task's id: the suite lerobot names when it holds one task (``pusht``,
    ``assembly-v3``), else ``<suite>/<task name>`` where the env names its task
    (``easy/assembly-v3``), else ``<suite>/<index>``."""
    if in_suite == 1:
        return suite
    return f"{suite}/{name}" if isinstance(name, str) and name else f"{suite}/{tid}"


def _step_budget(env: _OneOfVector, cfg: Any) -> int:
    """The steps lerobot-eval's rollout gives an episode: the env's ``_max_episode_steps``
    (what ``rollout`` reads), else the config's ``episode_length``."""
    steps = env.attr("_max_episode_steps") or getattr(cfg, "episode_length", None)
    if not steps:
        raise ValueError("env.params.max_steps: the env names no episode length; set it")
    return int(steps)


def mujoco_data(env: _OneOfVector) -> Any | None:
    """The ``mujoco.MjData`` under a lerobot env where it is a MuJoCo one (MetaWorld's
    ``_env.data``, ALOHA's dm_control ``_env.physics.data.ptr``), else None (PushT's pymunk).
    Only looked for once MuJoCo is imported: a type that does not use it never imports it."""
    if "mujoco" not in sys.modules:
        return None
    import mujoco

    sub = env.sub_env
    physics = _dm_control_physics(env)
    for data in (
        getattr(sub, "data", None),
        getattr(getattr(sub, "_env", None), "data", None),
        getattr(getattr(physics, "data", None), "ptr", None),
    ):
        if isinstance(data, mujoco.MjData):
            return data
    return None


def _dm_control_physics(env: _OneOfVector) -> Any | None:
    """The dm_control ``Physics`` under a lerobot env that has one (ALOHA), else None."""
    sub = env.sub_env
    for obj in (sub, getattr(sub, "_env", None)):
        physics = getattr(obj, "physics", None)
        if hasattr(physics, "free"):
            return physics
    return None


def _unbatch(obs: Any) -> Any:
    if isinstance(obs, Mapping):
        return {k: _unbatch(v) for k, v in obs.items()}
    return np.asarray(obs)[0]


class LerobotEnvSuite(GymnasiumEnv):
    """The tasks of one lerobot env type (see the module docstring)."""

    suite = "lerobot"
    # an env that describes no task (PushT, ALOHA) gives "", the instruction lerobot-eval feeds
    empty_instruction_ok = True

    def __init__(
        self,
        type: Annotated[str, Doc("the lerobot env type (pusht, aloha, metaworld, ...)")],
        instruction: Annotated[
            str | None, Doc("the instruction where the env describes no task")
        ] = None,
        max_steps: Annotated[
            int | None,
            Doc("control steps per episode; None: the env's own (what lerobot-eval reads)"),
        ] = None,
        success_key: Annotated[
            str,
            Doc(
                "the info key that says the task is done (lerobot-eval reads is_success; a "
                "plugin may report success under its own key)"
            ),
        ] = "is_success",
        **config: Any,
    ) -> None:
        if max_steps is not None and (not isinstance(max_steps, int) or max_steps <= 0):
            raise ValueError(f"env.params.max_steps={max_steps!r} must be an int > 0")
        from workers.rendering import configure_rendering

        configure_rendering()  # before a MuJoCo type imports mujoco (no-op if already chosen)
        if type in LIBERO_TYPES:
            raise ValueError(
                f"env.params.type={type!r}: its observation is lerobot's LIBERO robot_state, "
                f"not the pixels + agent_pos this suite reads; {LIBERO_TYPES[type]}"
            )
        self.cfg = env_config(type, config)
        self._build_vectors(type, success_key)
        cams, pixels = self._cameras(type)
        self.image_option = image_option(self.cfg) if pixels is None else None
        budgets = {k: max_steps or _step_budget(v, self.cfg) for k, v in self._vecs.items()}
        self.env_type = self.env_id = type
        self._setup(
            cams,
            ["agent_pos"],
            instruction,
            success_key,
            next(iter(budgets.values())),
            self.cfg.fps,
            "env.params",
        )
        self._fixed_instruction = instruction
        self._data: Any = None  # the current task's MjData, for a MuJoCo type
        self._specs = {
            tid: TaskSpec(
                tid,
                f"{type}:{tid}",
                int(budgets[tid]),
                suite=self._suite_of[tid],
                instruction=instruction,
            )
            for tid in self._vecs
        }

    def _build_vectors(self, type: str, success_key: str) -> None:
        """lerobot's vector envs, one per task (``self._vecs``), and each task's suite."""
        with self._missing_package(type):
            built = self.cfg.create_envs(n_envs=1, use_async_envs=False)
        self._suite_of: dict[str, str] = {}
        self._vecs: dict[str, _OneOfVector] = {}
        for suite, tasks in built.items():
            for tid, vec in tasks.items():
                one = _OneOfVector(vec, success_key)
                key = _task_key(str(suite), tid, one.attr("task"), len(tasks))
                self._suite_of[key], self._vecs[key] = str(suite), one
        self._env = next(iter(self._vecs.values()))

    def _cameras(self, type: str) -> tuple[dict[str, str], Any]:
        """camera -> observation path, and the pixels space (None: a state-only env, which runs
        the baseline mode; the pre-flight refuses the modes that intervene on an image, naming
        the config's image option)."""
        space = self._env.observation_space
        parts = getattr(space, "spaces", None) or {}
        pixels = parts.get("pixels")
        if "agent_pos" not in parts:
            raise ValueError(
                f"env.params.type={type!r}: its observation ({space}) has no agent_pos, which "
                "this suite reads as the state; for LIBERO use env.suite=libero"
            )
        if pixels is None:
            return {}, None
        if hasattr(pixels, "spaces"):
            return {k: f"pixels/{k}" for k in pixels.spaces}, pixels
        return {"image": "pixels"}, pixels

    def tasks(self) -> list[TaskSpec]:
        return list(self._specs.values())

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        if task_id not in self._specs:
            raise ValueError(f"task_id={task_id!r} unknown; allowed: {sorted(self._specs)}")
        self._clock = EpisodeClock(self.action_dim)  # no episode until this reset is through
        self._env = self._vecs[task_id]
        own_gl_context(self._env)
        with self._missing_package(self.env_type):  # types that import their simulator here
            obs, _ = self._env.reset(seed=int(seed) + int(episode_index))
        described = self._env.call("task_description") or self._env.call("task")
        self._instruction = str(described or self._fixed_instruction or "")
        self._data = mujoco_data(self._env)
        if self._data is not None:
            mujoco_instability(self._data)  # what an earlier episode left: cleared
        self._clock.start(self._specs[task_id])
        self._success, self._ended = False, False
        return self._observe(obs)

    def step(self, action: np.ndarray) -> EnvObservation:
        """One step; a MuJoCo type whose simulation diverged (MuJoCo resets it and carries on)
        raises SimulationUnstableError: an error row, not a scored episode."""
        obs = super().step(action)
        if self._data is not None:
            where = f"at step {self._clock.steps} of {obs.status.task_id}"
            raise_if_unstable(self._data, where)
        return obs

    def _held_envs(self) -> list[Any]:
        return list(self._vecs.values())

    def close(self) -> None:
        for vec in self._vecs.values():
            physics = _dm_control_physics(vec)
            release_gl_context(vec)
            vec.close()
            if physics is not None:
                # dm_control (ALOHA) frees its rendering contexts only when the physics is
                # collected; left to interpreter exit, that waits on its render thread, which
                # is gone by then (a process that never exits). Freed here, while it is alive.
                physics.free()
        self._data = None

    @contextlib.contextmanager
    def _missing_package(self, type: str) -> Iterator[None]:
        """A module lerobot's env imports and that is absent: a ValueError naming what to
        install (some types import it when built, some at their first reset)."""
        try:
            yield
        except ModuleNotFoundError as exc:
            package = exc.name or cfg_package(self.cfg)
            need = PACKAGES.get(type, f"the package that provides {package!r}")
            raise ValueError(
                f"env.params.type={type!r}: {package!r} is not installed; install {need}"
            ) from None

    @classmethod
    def describe(cls, **params: Any) -> EnvIO:
        """lerobot-eval's protocol: the checkpoint's n_action_steps per inference (``chunk``),
        lerobot's episode length, seed + episode index."""
        env = cls(**params)
        try:
            # one reset, as check_env does: a type that imports its simulator only then (VLABench,
            # RoboTwin) is refused here, before any actor, naming what to install
            env.reset(env.tasks()[0].task_id, 0, 0)
            env.step(np.zeros(env.action_dim, np.float32))  # its info names the success key
            if env.success_key not in env._env.info_keys:
                raise ValueError(
                    f"env.params.success_key={env.success_key!r}: the info of the pre-flight's "
                    f"step has no such key; env type {env.env_type!r} reports "
                    f"{env._env.info_keys}: set env.params.success_key to the one that says "
                    "the task is done"
                )
            io = env_io(env)
            protocol = {
                "name": "lerobot",
                "type": env.env_type,
                "max_steps": env._task_spec.max_steps,
                "success": f"info[{env.success_key!r}]",
                "seed": "run seed + episode index",
            }
            return dataclasses.replace(
                io, replan="chunk", protocol=protocol, image_option=env.image_option
            )
        finally:
            env.close()
