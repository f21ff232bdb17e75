"""Any registered Gymnasium env whose observation is a dict of camera images and state vectors.

``env.suite: gymnasium`` with ``env.params.id`` (a registered id; ``module:Id`` imports the
module that registers it first) and ``env.params.kwargs`` for ``gymnasium.make``. The config
maps the observation: ``images`` (camera name -> observation key, ``a/b`` for a nested dict;
default: every (H, W, 3) uint8 entry, under its own key), ``state`` (keys concatenated, in order;
default: every 1-D numeric entry, sorted by key), ``instruction`` (envs without one, such as
PushT, get this fixed string, recorded with every episode) and ``success_key`` (the ``info``
entry that says the task is done; ``is_success`` by Gymnasium's convention).

Envs whose observation is a state vector (MetaWorld's own ``Meta-World/MT1``, Gymnasium's MuJoCo
tasks) get their rendered frame as a camera with ``render_key`` (Gymnasium's
``AddRenderObservation``: the observation becomes ``{render_key: frame, "state": obs}``), at the
size the env's ``width`` / ``height`` kwargs give; ``render_quality`` sets MuJoCo's
``model.vis.quality`` fields before the first frame (software rendering spends most of a small
frame on the 4096 px shadow map and 4x multisampling: ``{shadowsize: 512, offsamples: 0}``). A
state entry may take a slice, ``state[0:4]``. ``tasks`` makes several tasks of one env id,
each with its own ``kwargs`` (merged over the shared ones) and ``instruction``; each task's env
is built at its first reset.

Episode ``i`` of a run with seed ``s`` resets with ``seed = s + i`` (lerobot-eval's rule with one
env). The episode ends at success, at ``terminated`` / ``truncated``, or after ``max_steps``
(default: the env spec's ``max_episode_steps``).
"""

from __future__ import annotations

import contextlib
import difflib
import importlib
import re
from collections.abc import Mapping
from typing import Annotated, Any

import numpy as np

from workers.envs.base import EnvObservation, EpisodeStatus, TaskSpec
from workers.envs.episode_clock import EpisodeClock
from workers.io_spec import EnvIO
from workers.param_doc import Doc
from workers.rendering import own_gl_context, release_gl_context

DEFAULT_INSTRUCTION = "do the task"


def import_registering_module(env_id: str) -> str:
    """``module:Id`` -> Id with ``module`` imported; ``namespace/Id`` -> the namespace module
    imported when it exists (gym_pusht registers gym_pusht/PushT-v0 on import)."""
    if ":" in env_id:
        module, env_id = env_id.split(":", 1)
        importlib.import_module(module)
        return env_id
    if "/" in env_id:
        with contextlib.suppress(ModuleNotFoundError):
            importlib.import_module(env_id.split("/", 1)[0])
    return env_id


def check_registered(env_id: str) -> str:
    """The registered id, or a ValueError naming the field, close ids and how to register."""
    import gymnasium as gym

    try:
        bare = import_registering_module(env_id)
    except ModuleNotFoundError as exc:
        raise ValueError(
            f"env.params.id={env_id!r}: module {exc.name!r} is not installed (it registers the "
            "env): install its package"
        ) from None
    if bare not in gym.registry:
        close = difflib.get_close_matches(bare, list(gym.registry), n=3, cutoff=0.6)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        namespace = bare.split("/", 1)[0] if "/" in bare else None
        pkg = f"; install the package that registers {namespace!r}" if namespace else ""
        raise ValueError(f"env.params.id={env_id!r} is not a registered Gymnasium env{hint}{pkg}")
    return bare


_SLICE = re.compile(r"^(?P<path>.+)\[(?P<lo>\d*):(?P<hi>\d*)\]$")


def _split_slice(path: str) -> tuple[str, slice | None]:
    """``state[0:4]`` -> ("state", slice(0, 4)); a plain path -> (path, None)."""
    m = _SLICE.match(path)
    if m is None:
        return path, None
    lo, hi = m["lo"], m["hi"]
    return m["path"], slice(int(lo) if lo else None, int(hi) if hi else None)


def _get(obs: Mapping[str, Any], path: str) -> Any:
    path, part_of = _split_slice(path)
    node: Any = obs
    for part in path.split("/"):
        if not isinstance(node, Mapping) or part not in node:
            return None
        node = node[part]
    return node if part_of is None else np.asarray(node).reshape(-1)[part_of]


def _leaves(space: Any, prefix: str = "") -> dict[str, Any]:
    """Observation-space leaves by ``a/b`` path."""
    spaces = getattr(space, "spaces", None)
    if not isinstance(spaces, Mapping):
        return {prefix.rstrip("/"): space} if prefix else {}
    out: dict[str, Any] = {}
    for key, sub in spaces.items():
        out |= (
            _leaves(sub, f"{prefix}{key}/")
            if isinstance(getattr(sub, "spaces", None), Mapping)
            else {f"{prefix}{key}": sub}
        )
    return out


def _leaf_len(leaves: Mapping[str, Any], key: str) -> int:
    path, part_of = _split_slice(key)
    n = int(np.prod(leaves[path].shape))
    return n if part_of is None else len(range(n)[part_of])


def _is_image(space: Any) -> bool:
    shape = getattr(space, "shape", None)
    return shape is not None and len(shape) == 3 and shape[-1] == 3 and space.dtype == np.uint8


def _is_vector(space: Any) -> bool:
    shape = getattr(space, "shape", None)
    return shape is not None and len(shape) == 1 and np.issubdtype(space.dtype, np.number)


def map_observation(
    space: Any,
    leaves: Mapping[str, Any],
    images: Mapping[str, str] | None,
    state: list[str] | str | None,
    where: str,
) -> tuple[dict[str, str], list[str]]:
    """(camera -> observation path, state paths) checked against the observation space's
    ``leaves`` (by ``a/b`` path)."""
    if not leaves:
        raise ValueError(
            f"{where}: the observation is not a dict (space {space}); this suite needs a dict "
            "of camera images and state vectors"
        )
    cams = (
        dict(images)
        if images is not None
        else {k.replace("/", "_"): k for k, s in leaves.items() if _is_image(s)}
    )
    keys = (
        [state]
        if isinstance(state, str)
        else list(state)
        if state is not None
        else sorted(k for k, s in leaves.items() if _is_vector(s))
    )
    for role, paths in (("images", list(cams.values())), ("state", keys)):
        missing = [p for p in paths if _split_slice(p)[0] not in leaves]
        if missing:
            raise ValueError(
                f"{where}.{role}: {missing} not in the observation (it has {sorted(leaves)})"
            )
    for cam, path in cams.items():
        if not _is_image(leaves[path]):
            raise ValueError(
                f"{where}.images.{cam}: {path!r} is {leaves[path]}, not an (H, W, 3) uint8 image"
            )
    if not cams and images is None:  # {}: a state-only env, asked for (lerobot's plugins)
        raise ValueError(f"{where}.images: no (H, W, 3) uint8 entry in {sorted(leaves)}")
    if not keys:
        raise ValueError(f"{where}.state: no 1-D numeric entry in {sorted(leaves)}")
    return cams, keys


class GymnasiumEnv:
    """One Gymnasium env as a suite with one task (see the module docstring)."""

    suite = "gymnasium"

    def __init__(
        self,
        id: Annotated[str, Doc("the registered Gymnasium id")],
        kwargs: Annotated[
            dict[str, Any] | None, Doc("keyword arguments for gymnasium.make")
        ] = None,
        images: Annotated[
            dict[str, str] | None,
            Doc("camera name -> the observation key of its image; None: every image leaf"),
        ] = None,
        state: Annotated[
            list[str] | str | None,
            Doc("the observation keys concatenated into the state; None: every vector leaf"),
        ] = None,
        instruction: Annotated[str | None, Doc("the instruction of every episode")] = None,
        success_key: Annotated[str, Doc("the info key that says the task is done")] = "is_success",
        max_steps: Annotated[
            int | None, Doc("control steps per episode; None: the spec's max_episode_steps")
        ] = None,
        control_hz: Annotated[
            float | None, Doc("control steps per second; None: the env's render_fps (else 10)")
        ] = None,
        tasks: Annotated[
            dict[str, dict[str, Any]] | None,
            Doc("task name -> {kwargs, instruction}: variants of the env as tasks"),
        ] = None,
        render_key: Annotated[
            str | None,
            Doc(
                "for a state-vector env: the camera its rendered frame becomes (AddRenderObservation)"
            ),
        ] = None,
        render_quality: Annotated[
            dict[str, int] | None,
            Doc(
                "MuJoCo model.vis.quality fields set before the first frame, e.g. {shadowsize: 512}"
            ),
        ] = None,
    ) -> None:
        from workers.rendering import configure_rendering

        configure_rendering()  # before a MuJoCo env imports mujoco (no-op if already chosen)
        self.env_id = check_registered(id)
        self._render_key = render_key
        self._render_quality = dict(render_quality or {})
        self._variants = _variants(tasks, kwargs, instruction)
        self._envs: dict[str, Any] = {}
        first = next(iter(self._variants))
        self._env = self._make(first)
        self._envs[first] = self._env
        self._setup(images, state, instruction, success_key, max_steps, control_hz, "env.params")
        if tasks:
            base = self._task_spec
            self._task_specs = {
                name: TaskSpec(
                    name, f"{self.env_id}:{name}", base.max_steps, instruction=v["instruction"]
                )
                for name, v in self._variants.items()
            }

    def _make(self, task: str) -> Any:
        import gymnasium as gym

        env = gym.make(self.env_id, disable_env_checker=True, **self._variants[task]["kwargs"])
        if self._render_quality:
            quality = getattr(getattr(env.unwrapped, "model", None), "vis", None)
            if quality is None:
                raise ValueError(
                    f"env.params.render_quality: {self.env_id} is not a MuJoCo env (no "
                    "model.vis); drop the key"
                )
            for key, value in self._render_quality.items():
                if not hasattr(quality.quality, key):
                    raise ValueError(
                        f"env.params.render_quality.{key}: not a MuJoCo model.vis.quality field "
                        "(e.g. shadowsize, offsamples)"
                    )
                setattr(quality.quality, key, value)
        if self._render_key is not None:
            from gymnasium.wrappers import AddRenderObservation

            if env.render_mode != "rgb_array":
                raise ValueError(
                    "env.params.render_key: the env must render frames; add render_mode: "
                    "rgb_array to env.params.kwargs"
                )
            env = AddRenderObservation(env, render_only=False, render_key=self._render_key)
        return env

    def _setup(
        self,
        images: Mapping[str, str] | None,
        state: list[str] | str | None,
        instruction: str | None,
        success_key: str,
        max_steps: int | None,
        control_hz: float | None,
        where: str,
    ) -> None:
        env = self._env
        leaves = _leaves(env.observation_space)
        self._cams, self._state_keys = map_observation(
            env.observation_space, leaves, images, state, where
        )
        self.cameras = tuple(self._cams)
        self.state_dim = int(sum(_leaf_len(leaves, k) for k in self._state_keys))
        self.action_dim = int(env.action_space.shape[0])
        self.image_sizes = {c: tuple(leaves[p].shape[:2]) for c, p in self._cams.items()}
        spec_steps = env.spec.max_episode_steps if env.spec is not None else None
        steps = max_steps or spec_steps
        if not steps:
            raise ValueError(f"{where}.max_steps: the env spec names no max_episode_steps; set it")
        fps = control_hz or env.metadata.get("render_fps") or 10
        self.control_hz = float(fps)
        self.success_key = success_key
        self._instruction = instruction or DEFAULT_INSTRUCTION
        self._task_spec = TaskSpec(
            self.env_id.replace("/", "_"), self.env_id, int(steps), instruction=self._instruction
        )
        self._clock = EpisodeClock(self.action_dim)
        self._success, self._ended = False, False

    # -- the Env protocol -----------------------------------------------------------------------
    def tasks(self) -> list[TaskSpec]:
        return list(
            getattr(self, "_task_specs", {self._task_spec.task_id: self._task_spec}).values()
        )

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        specs = {t.task_id: t for t in self.tasks()}
        if task_id not in specs:
            raise ValueError(f"task_id={task_id!r} unknown; allowed: {sorted(specs)}")
        self._clock = EpisodeClock(self.action_dim)  # no episode until this reset is through
        if hasattr(self, "_task_specs"):
            if task_id not in self._envs:
                self._envs[task_id] = self._make(task_id)
            self._env = self._envs[task_id]
            self._instruction = specs[task_id].instruction or self._instruction
        own_gl_context(self._env)
        obs, _ = self._env.reset(seed=int(seed) + int(episode_index))
        self.raw_observation = obs
        self._clock.start(specs[task_id])
        self._success, self._ended = False, False
        return self._observe(obs)

    def step(self, action: np.ndarray) -> EnvObservation:
        action = self._clock.take(action).astype(np.float32)
        own_gl_context(self._env)
        obs, _, terminated, truncated, info = self._env.step(action)
        self.raw_observation = obs  # as the env gave it (a scripted expert reads its state)
        self._success = self._success or bool(info.get(self.success_key, False))
        self._ended = bool(terminated or truncated)
        return self._observe(obs)

    def _observe(self, obs: Mapping[str, Any]) -> EnvObservation:
        images = {c: np.ascontiguousarray(_get(obs, p)) for c, p in self._cams.items()}
        state = np.concatenate(
            [np.asarray(_get(obs, k), dtype=np.float32).reshape(-1) for k in self._state_keys]
        )
        return EnvObservation(images=images, state=state, status=self._status())

    def _status(self) -> EpisodeStatus:
        return self._clock.status(
            self._instruction, self._success, ended=self._success or self._ended
        )

    def _held_envs(self) -> list[Any]:
        """Every Gymnasium env this suite holds (one per task where tasks are variants)."""
        return list(getattr(self, "_envs", {}).values()) or [self._env]

    def close(self) -> None:
        for env in self._held_envs():
            release_gl_context(env)
            env.close()

    def __del__(self) -> None:
        # an env dropped without close(): its MuJoCo GL objects are freed under its own
        # context, not under whichever env's context is current when the collector runs
        try:
            for env in self._held_envs():
                release_gl_context(env)
        except Exception:  # interpreter shutdown, or __init__ failed: nothing to protect
            pass

    # -- pre-flight ------------------------------------------------------------------------------
    @classmethod
    def describe(cls, **params: Any) -> EnvIO:
        env = cls(**params)
        try:
            return env_io(env)
        finally:
            env.close()


def _variants(
    tasks: dict[str, dict[str, Any]] | None, kwargs: dict[str, Any] | None, instruction: str | None
) -> dict[str, dict[str, Any]]:
    """Task name -> {kwargs, instruction}; one unnamed task without ``tasks``."""
    if not tasks:
        return {"": {"kwargs": dict(kwargs or {}), "instruction": instruction}}
    if not isinstance(tasks, Mapping):
        raise ValueError(
            "env.params.tasks: write a mapping task name -> {kwargs: {...}, instruction: ...}"
        )
    out = {}
    for name, v in tasks.items():
        v = dict(v or {})
        unknown = set(v) - {"kwargs", "instruction"}
        if unknown:
            raise ValueError(
                f"env.params.tasks.{name}: unknown keys {sorted(unknown)}; a task has kwargs "
                "and instruction"
            )
        out[str(name)] = {
            "kwargs": {**(kwargs or {}), **(v.get("kwargs") or {})},
            "instruction": v.get("instruction") or instruction,
        }
    return out


def env_io(env: Any) -> EnvIO:
    """What a built gymnasium-suite env renders and accepts: each camera's (height, width)."""
    sizes = {c: (int(h), int(w)) for c, (h, w) in env.image_sizes.items()}
    square = {s[0] for s in sizes.values() if s[0] == s[1]}
    first = min(square) if square else next(iter(sizes.values()), (0, 0))[0]  # 0: no camera
    return EnvIO(
        cameras=env.cameras,
        image_size=first,
        state_dim=env.state_dim,
        action_dim=env.action_dim,
        camera_sizes={
            c: (s[0] if s[0] == s[1] else s) for c, s in sizes.items() if s != (first, first)
        },
    )
