"""The ``tabletop`` suite: tasks that need the image and the instruction, on robosuite.

Panda with OSC_POSE control at 20 Hz; action 7-d (end-effector position and axis-angle
deltas in [-1, 1], gripper -1 open / +1 close); state 8-d like LIBERO's (end-effector
position, axis-angle, two gripper joint positions); an agent-view and a wrist camera.

- ``pick_color``: red, green and blue cubes at random places; "pick up the <color> cube" with
  the color drawn per episode. Without the image the cube cannot be found; without the
  instruction the wrong one is picked two times out of three.
- ``stack_color``: "stack the <a> cube on the <b> cube" (a, b drawn per episode).
- ``organize``: five cubes and a bin; "put the <c1>, <c2>, <c3>, <c4> and <c5> cubes in the
  bin, in that order": a chain of five subtasks, CALVIN-style. The episode stops at the
  first failure: a cube put in the bin out of order, or a subtask not done within
  ``subtask_budget`` steps.

Initial states come from (seed, episode index, task), so every cell of a grid sees the same
scenes. The env also exposes privileged simulator state (``EnvObservation.privileged``) for
the scripted experts; policies never see it. ``object_hidden_images`` renders the current state
with the objects the instruction names left out (Policy Contrastive Decoding's object-removed
image, arXiv 2505.13255). Beside this module: ``episodes`` (the layouts,
instructions and scoring rules), ``sim`` (the robosuite scene), ``layout`` (its dimensions).
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar

import numpy as np

from workers.envs.base import EnvObservation, EpisodeInfo, LazyImages, LazyState, TaskSpec
from workers.envs.episode_clock import EpisodeClock
from workers.envs.mujoco.stability import mujoco_instability, raise_if_unstable
from workers.envs.suites.tabletop.episodes import Episode, free_spots, new_episode, update_progress
from workers.io_spec import ROBOSUITE_CAMERA_ALIASES, EnvIO
from workers.param_doc import Doc

SUITE = "tabletop"
CAMERAS = {"agentview": "agentview", "wrist": "robot0_eye_in_hand"}
DEFAULT_MAX_STEPS = {"pick_color": 120, "stack_color": 220, "organize": 1000}
DEFAULT_SUBTASK_BUDGET = 200


class TabletopEnv:
    """The tabletop suite behind the Env protocol (one robosuite scene per task, reused)."""

    suite = SUITE
    control_hz = 20.0
    action_dim = 7
    state_dim = 8
    gripper_index = 6
    #: object_hidden_images: the current state rendered without the instruction's objects
    renders_hidden_objects = True

    #: scene perturbations this suite applies (workers/envs/wrappers/perturbations.py)
    perturbation_kinds = (
        "camera_shift",
        "camera_pitch",
        "light_dim",
        "table_color",
        "init_jitter",
        "distractors",
    )

    TASK_COLORS: ClassVar[dict[str, tuple[str, ...]]] = {
        "pick_color": ("red", "green", "blue"),
        "stack_color": ("red", "green", "blue"),
        "organize": ("red", "green", "blue", "yellow", "purple"),
    }
    TASK_NAMES: ClassVar[dict[str, str]] = {
        "pick_color": "pick up the named cube",
        "stack_color": "stack one named cube on another",
        "organize": "put five cubes in the bin in the instructed order",
    }

    def __init__(
        self,
        image_size: Annotated[int, Doc("px per side of every camera image")] = 96,
        cameras: Annotated[
            tuple[str, ...] | list[str], Doc("the cameras rendered: agentview, wrist")
        ] = ("agentview", "wrist"),
        max_steps: Annotated[
            dict[str, int] | None,
            Doc("task -> control steps before a timeout, over the defaults"),
        ] = None,
        subtask_budget: Annotated[
            int, Doc("organize: steps each subtask may take before the chain fails")
        ] = DEFAULT_SUBTASK_BUDGET,
        fast_render: Annotated[
            bool,
            Doc("drop MSAA, reflections, skybox and shadows (several x cheaper)"),
        ] = True,
        state_dims: Annotated[
            list[int] | None,
            Doc("which of the 8 state dims the policy gets, e.g. [0,1,2,6,7]; None: all"),
        ] = None,
    ) -> None:
        self.state_dims = self._check_state_dims(state_dims)
        if self.state_dims is not None:
            self.state_dim = len(self.state_dims)
        if image_size <= 0:
            raise ValueError(f"env.params.image_size={image_size} must be > 0")
        unknown = [c for c in cameras if c not in CAMERAS]
        if unknown or not cameras:
            raise ValueError(
                f"env.params.cameras={list(cameras)}: choose one or more of {list(CAMERAS)}"
            )
        self._max_steps = self._check_max_steps(max_steps)
        if subtask_budget <= 0:
            raise ValueError(f"env.params.subtask_budget={subtask_budget} must be > 0")
        self.subtask_budget = subtask_budget
        self.image_size = image_size
        self.cameras = tuple(cameras)
        self.fast_render = fast_render  # no MSAA/reflections/skybox/shadows: ~3x cheaper on OSMesa
        self._scenes: dict[str, Any] = {}
        self._renderers: dict[str, Any] = {}
        self._perturbers: dict[str, Any] = {}
        self._perturbation: Any = None  # for the next reset (set_perturbation)
        self._ep: Episode | None = None
        self._clock = EpisodeClock(self.action_dim)

    @staticmethod
    def _check_max_steps(max_steps: dict[str, int] | None) -> dict[str, int]:
        merged = {**DEFAULT_MAX_STEPS, **(max_steps or {})}
        bad = {k: v for k, v in merged.items() if k not in DEFAULT_MAX_STEPS or int(v) <= 0}
        if bad:
            raise ValueError(
                f"env.params.max_steps={bad}: tasks are {list(DEFAULT_MAX_STEPS)}, steps > 0"
            )
        return {k: int(v) for k, v in merged.items()}

    @classmethod
    def suite_tasks(cls, max_steps: dict[str, int] | None = None, **_: Any) -> list[TaskSpec]:
        steps = cls._check_max_steps(max_steps)
        return [
            TaskSpec(t, cls.TASK_NAMES[t], steps[t], 5 if t == "organize" else 1, suite=SUITE)
            for t in DEFAULT_MAX_STEPS
        ]

    @classmethod
    def _check_state_dims(cls, dims: list[int] | None) -> tuple[int, ...] | None:
        """``state_dims``: which of the 8 state dims the policy gets, e.g. [0, 1, 2, 6, 7] (no
        orientation: the zoo's lerobot architectures, training/zoo_state.py). None: all."""
        if dims is None:
            return None
        dims = list(dims)
        if (
            not dims
            or len(set(dims)) != len(dims)
            or any(not isinstance(d, int) or not 0 <= d < cls.state_dim for d in dims)
        ):
            raise ValueError(
                f"env.params.state_dims={dims}: distinct dims of the {cls.state_dim}-d state "
                "(0-2 position, 3-5 orientation, 6-7 gripper), e.g. [0, 1, 2, 6, 7]"
            )
        return tuple(dims)

    @classmethod
    def describe(
        cls,
        image_size: int = 96,
        cameras: tuple[str, ...] | list[str] = ("agentview", "wrist"),
        state_dims: list[int] | None = None,
        **_: Any,
    ) -> EnvIO:
        """What the suite gives a policy (docs/suites/index.md): images uint8 at ``image_size``
        px, not flipped; state and action as LIBERO's; no protocol beyond its params."""
        return EnvIO(
            cameras=tuple(cameras),
            image_size=int(image_size),
            state_dim=len(dims) if (dims := cls._check_state_dims(state_dims)) else cls.state_dim,
            action_dim=cls.action_dim,
            camera_aliases={c: ROBOSUITE_CAMERA_ALIASES[c] for c in cameras if c in CAMERAS},
        )

    def tasks(self) -> list[TaskSpec]:
        return self.suite_tasks(self._max_steps)

    # -- scenes ----------------------------------------------------------------------------
    def _scene(self, key: str) -> Any:
        """The scene of a task (``pick_color``), or of a task with n distractor cubes
        (``pick_color+d2``: a scene of its own, so that the task's own scene never has them)."""
        if key not in self._scenes:
            from workers.envs.suites.tabletop.sim import FastRenderer, make_scene

            task_id, _, n = key.partition("+d")
            scene = make_scene(
                self.TASK_COLORS[task_id], with_bin=task_id == "organize", n_distractors=int(n or 0)
            )
            self._scenes[key] = scene
            cams = {c: CAMERAS[c] for c in self.cameras}
            self._renderers[key] = FastRenderer(scene, cams, self.image_size, self.fast_render)
        return self._scenes[key]

    def set_perturbation(self, p: Any) -> None:
        """The scene perturbation of the next reset (None: the unperturbed scene)."""
        if p is not None and p.kind not in self.perturbation_kinds:
            raise ValueError(
                f"tabletop cannot apply {p.kind}; it applies {self.perturbation_kinds}"
            )
        self._perturbation = p

    def _perturber(self, task_id: str, scene: Any) -> Any:
        if task_id not in self._perturbers:
            from workers.envs.mujoco.scene_edits import MujocoScenePerturber

            self._perturbers[task_id] = MujocoScenePerturber(
                scene.sim.model._model, CAMERAS["agentview"], ["table_visual"]
            )
        return self._perturbers[task_id]

    # -- episode -----------------------------------------------------------------------------
    def _spec(self, task_id: str) -> TaskSpec:
        for t in self.tasks():
            if t.task_id == task_id:
                return t
        raise ValueError(
            f"task_id={task_id!r} is not a tabletop task; valid: {list(DEFAULT_MAX_STEPS)}"
        )

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        spec = self._spec(task_id)
        task_index = list(DEFAULT_MAX_STEPS).index(task_id)
        ep = new_episode(task_id, task_index, self.TASK_COLORS[task_id], episode_index, seed)
        p = self._perturbation
        if p is not None and p.kind == "distractors":
            ep.scene_key = f"{task_id}+d{int(p.severity)}"
        scene = self._scene(ep.scene_key)
        if self._perturbers or p is not None:  # a perturbed episode ran here: undo it first
            self._perturber(ep.scene_key, scene).restore()
        distractor_xy = None
        if p is not None and p.kind in ("init_jitter", "distractors"):  # the layout changes
            from workers.envs.wrappers.perturbation_grammar import join_task

            rng = p.rng(seed, join_task(task_id, p), episode_index)
            if p.kind == "init_jitter":  # each cube moved by up to severity
                ep.cube_xy = ep.cube_xy + rng.uniform(-p.severity, p.severity, ep.cube_xy.shape)
            else:
                distractor_xy = free_spots(rng, ep.cube_xy, int(p.severity), task_id == "organize")
            ep.init_state_id = join_task(ep.init_state_id, p)
        scene.place_cubes(ep.cube_xy, distractor_xy)
        self._last_obs = scene.reset()
        if p is not None and p.kind not in ("init_jitter", "distractors"):
            self._perturber(ep.scene_key, scene).apply(p, scene.sim.data._data)
        mujoco_instability(scene.sim.data._data)  # clear what earlier episodes left
        self._ep = ep
        self._clock.start(spec)
        return self._observe()

    def step(self, action: np.ndarray) -> EnvObservation:
        action = self._clock.take(action)
        assert self._ep is not None
        scene = self._scenes[self._ep.scene_key]
        data = scene.sim.data._data
        self._last_obs, _, _, _ = scene.step(np.clip(action, -1.0, 1.0))
        steps = self._clock.steps
        raise_if_unstable(data, f"at step {steps} of {self._ep.init_state_id}")
        update_progress(self._ep, scene, self.subtask_budget, steps)
        return self._observe()

    def _observe(self) -> EnvObservation:
        from robosuite.utils.transform_utils import quat2axisangle

        o = self._last_obs
        state = np.concatenate(
            [o["robot0_eef_pos"], quat2axisangle(o["robot0_eef_quat"]), o["robot0_gripper_qpos"]]
        ).astype(np.float32)
        if self.state_dims is not None:
            state = state[list(self.state_dims)]
        # rendering and the privileged state read the live simulator: valid until the next step
        ep, clock, steps = self._ep, self._clock, self._clock.steps

        def current() -> bool:
            return self._ep is ep and clock.steps == steps

        images = LazyImages(self.cameras, self._renderers[ep.scene_key].render_one, current)
        status = self._clock.status(
            ep.instruction,
            ep.success,
            ended=ep.success or bool(ep.failed),
            subtasks_done=ep.subtasks_done,
            info=EpisodeInfo(ep.init_state_id, ep.failed_cause, ep.failed),
        )
        return EnvObservation(
            images=images,
            state=state,
            privileged=LazyState(self.privileged, current),
            status=status,
        )

    def hidden_object_geoms(self) -> tuple[int, ...]:
        """Ids of the geoms ``object_hidden_images`` hides in the current episode: every geom
        (collision and visual) of each object the instruction names, the objects a policy
        must see to do the task, which Policy Contrastive Decoding takes out of the image:

        - ``pick_color``: the named cube;
        - ``stack_color``: the cube to stack and the cube to stack it on;
        - ``organize``: the five cubes and the bin's five parts (floor and walls).

        Cubes the instruction does not name (the third cube of pick_color and stack_color)
        and the grey cubes of the ``distractors`` perturbation stay: they are the scene the
        objects are contrasted against. The robot, table and arena stay."""
        ep = self._require_episode("hidden_object_geoms")
        scene = self._scenes[ep.scene_key]
        return scene.object_geoms(ep.targets, with_bin=ep.task_id == "organize")

    def object_hidden_images(self) -> dict[str, np.ndarray]:
        """The current state from every camera of the observation, with the instruction's
        objects hidden (``hidden_object_geoms``): uint8 (H, W, 3) like ``EnvObservation.images``
        (same renderer, size and look, not flipped; scene perturbations included, since they
        edit the model), and equal to them to the bit wherever the objects are not seen. What
        the objects covered shows; their shadows and reflections are off in the fast look,
        with ``fast_render=False`` those go too.

        The objects' geoms get alpha 0 for this render only
        (``workers.envs.mujoco.scene_edits.geoms_hidden``), their rgba restored to the bit
        after it: the simulation is not touched, and every later observation is what it would
        have been without the call. Image perturbations (image_noise...) are the wrapper's
        (``PerturbedEnv.object_hidden_images``). It renders every camera (about one camera's
        render each, docs/suites/tabletop.md); call it after a reset, before the next step."""
        ep = self._require_episode("object_hidden_images")
        return self._renderers[ep.scene_key].render_without(self.hidden_object_geoms())

    def _require_episode(self, what: str) -> Episode:
        if self._ep is None:
            raise RuntimeError(f"{what}() before reset()")
        return self._ep

    def privileged(self) -> dict[str, Any]:
        """Simulator state for the scripted experts (never for learned policies)."""
        ep = self._ep
        scene = self._scenes[ep.scene_key]
        return {
            "task_id": ep.task_id,
            "cube_pos": scene.cube_positions(),
            "targets": list(ep.targets),
            "subtasks_done": ep.subtasks_done,
            "eef_pos": np.asarray(self._last_obs["robot0_eef_pos"], dtype=float),
            "gripper_qpos": np.asarray(self._last_obs["robot0_gripper_qpos"], dtype=float),
            "grasped": [scene.is_grasped(i) for i in range(len(ep.colors))],
        }

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        for s in self._scenes.values():
            s.close()
        self._renderers, self._scenes, self._ep = {}, {}, None
        self._clock = EpisodeClock(self.action_dim)
