"""The ``simpler`` suite: SIMPLER (Li et al., SimplerEnv) as its official evaluator runs it.

What ``simpler_env/evaluation/maniskill2_evaluator.py`` and the ``scripts/`` grids do, and this
adapter with it (the tables are beside it: ``protocol``, ``grids``, ``assets``):

- a task is a SimplerEnv task under one setup, ``google_robot_open_top_drawer/visual_matching``;
  episode ``e`` is the ``e``-th episode of the official list (robot pose, object position or
  episode id, URDF recolour, overlay, scene and variant kwargs, as the scripts enumerate them);
- each episode gets a freshly built env (``gym.make`` with the script's kwargs, as the evaluator
  does), reset with the episode's ``robot_init_options`` / ``obj_init_options`` and no seed:
  the env's own main seed (2022) makes it deterministic, so the run's seed does not enter;
- success: ``info['success']`` of the final step, the episode running its max steps (80 / 113 /
  200 for Google, 60 / 120 for WidowX); ``success_rule=any_step`` ends at the first success
  instead (not SimplerEnv's rule; recorded with the run);
- observation: the task's official camera as ``image`` (Google ``overhead_camera`` 512x640,
  WidowX ``3rd_view_camera`` 480x640, uint8, the real-image overlay in visual matching), the
  state (8,): TCP position (3) and axis-angle (3) in the robot base frame, finger joints (2);
- actions: 7-d, converted by ``simpler_protocol.to_sim_action`` (rotation as axis-angle or
  roll-pitch-yaw, Google's relative gripper, WidowX's absolute one);
- the apple task switches its instruction from "open top drawer" to "place apple into top
  drawer" at step 100 (the env does; no policy here predicts termination, as with Octo).

ManiSkill2_real2sim (Apache-2.0) and SAPIEN 2.2.2 (wheels up to Python 3.11) run in an env
server (``env.python``: ``make setup-simpler`` creates ``.venv-simpler``); the checkout comes
from ``env.params.maniskill2_real2sim``, ``$MS2_REAL2SIM`` or ``$SIMPLER_ENV/ManiSkill2_real2sim``
and is never copied. Rendering is Vulkan: a GPU's driver, or lavapipe on a CPU
(``workers.envs.suites.simpler.vulkan_cpu``); renderer and shader are recorded with every episode.
"""

from __future__ import annotations

import inspect
import os
import sys
from collections.abc import Sequence
from typing import Annotated, Any

import numpy as np

from workers.envs.base import EnvObservation, EpisodeInfo, EpisodeStatus, LazyState, TaskSpec
from workers.envs.episode_clock import EpisodeClock
from workers.envs.suites.simpler import protocol as sp
from workers.envs.suites.simpler import vulkan_cpu as vk
from workers.envs.suites.simpler.assets import checkout, missing_assets
from workers.envs.suites.simpler.grids import TASKS, episodes_of, split_task_id
from workers.envs.suites.simpler.state import privileged_state, robot_state
from workers.io_spec import EnvIO
from workers.param_doc import Doc

SUITE = "simpler"
SHADERS = ("official", "ibl", "rt")
SETUP_HINT = (
    "make setup-simpler creates .venv-simpler (Python 3.11 + SAPIEN 2.2.2) and .vulkan-cpu; "
    "then set env.python=.venv-simpler/bin/python"
)
RT_ON_CPU = (
    "ray tracing (shader rt, the official shader of the drawer and apple tasks) on lavapipe takes "
    "~80 s per step here: set env.params.shader=ibl (recorded with every episode as a deviation "
    "from the official protocol), or render on a GPU"
)


class SimplerEnv:
    """SIMPLER's official evaluation behind the Env protocol (see the module docstring)."""

    suite = SUITE
    action_dim = 7
    state_dim = 8
    gripper_index = 6
    cameras = ("image",)
    server_setup_hint = SETUP_HINT

    def __init__(
        self,
        maniskill2_real2sim: Annotated[
            str | None, Doc("the ManiSkill2_real2sim checkout; None: $MS2_REAL2SIM or $SIMPLER_ENV")
        ] = None,
        renderer: Annotated[
            str,
            Doc(
                "Vulkan: auto (gpu where a GPU driver is installed, else lavapipe), gpu or lavapipe"
            ),
        ] = "auto",
        vulkan_cpu: Annotated[
            str | None,
            Doc(
                "the prefix make setup-simpler builds lavapipe into; None: $IDR_VULKAN_CPU or .vulkan-cpu"
            ),
        ] = None,
        shader: Annotated[
            str, Doc("official (rt for the drawer and apple tasks, ibl for the others), ibl or rt")
        ] = "official",
        success_rule: Annotated[
            str,
            Doc(
                "final_step (the official: the last step's success) or any_step (ends at the first)"
            ),
        ] = "final_step",
        rotation: Annotated[
            str, Doc("the action's rotation: axis_angle (SimplerEnv, RT-1) or rpy")
        ] = "axis_angle",
        binarize_gripper: Annotated[bool, Doc("round the gripper action to open / close")] = False,
    ) -> None:
        self._check_params(maniskill2_real2sim, renderer, shader, success_rule, rotation)
        self.checkout = checkout(maniskill2_real2sim)
        self.data = self.checkout / "data"
        self.renderer = vk.resolve(renderer, vulkan_cpu)
        self.driver = "gpu" if self.renderer == "gpu" else vk.configure(vulkan_cpu)
        self.shader, self.success_rule = shader, success_rule
        self._shader = shader  # the one the current episode's env renders with (_build)
        self.rotation, self.binarize = rotation, bool(binarize_gripper)
        if str(self.checkout) not in sys.path:
            sys.path.insert(0, str(self.checkout))
        os.environ["MS2_REAL2SIM_ASSET_DIR"] = str(self.data)
        self._specs = {t.task_id: t for t in self.suite_tasks()}
        self._env: Any = None
        self._clock = EpisodeClock(self.action_dim)
        self._episode: sp.Episode | None = None
        self._robot: sp.Robot = sp.GOOGLE
        self._success = False
        self._instruction = ""
        self._obs: dict[str, Any] = {}
        self._generation = 0

    # -- params, without a simulator ---------------------------------------------------------
    @staticmethod
    def _check_params(
        maniskill2_real2sim: str | None,
        renderer: str,
        shader: str,
        success_rule: str,
        rotation: str,
    ) -> None:
        if renderer not in vk.RENDERERS:
            raise ValueError(f"env.params.renderer={renderer!r}: one of {list(vk.RENDERERS)}")
        if shader not in SHADERS:
            raise ValueError(
                f"env.params.shader={shader!r}: one of {list(SHADERS)} (official: rt for the "
                "drawer and apple tasks, ibl for the others, as the scripts)"
            )
        if success_rule not in sp.SUCCESS_RULES:
            raise ValueError(
                f"env.params.success_rule={success_rule!r}: one of {list(sp.SUCCESS_RULES)}"
            )
        if rotation not in sp.ROTATIONS:
            raise ValueError(f"env.params.rotation={rotation!r}: one of {list(sp.ROTATIONS)}")

    @classmethod
    def _checked(cls, params: dict[str, Any]) -> dict[str, Any]:
        """The constructor's params with its defaults filled in, checked (no checkout yet)."""
        bound = inspect.signature(cls).bind(**params)
        bound.apply_defaults()
        p = bound.arguments
        cls._check_params(
            p["maniskill2_real2sim"], p["renderer"], p["shader"], p["success_rule"], p["rotation"]
        )
        return p

    @classmethod
    def suite_tasks(cls, **_: Any) -> list[TaskSpec]:
        return [
            TaskSpec(
                task_id=f"{name}/{setup}",
                name=f"{name} ({setup}, {len(episodes)} official episodes)",
                max_steps=task.max_steps,
                suite=SUITE,
                instruction=task.instruction,
                episodes_total=len(episodes),
            )
            for name, task in TASKS.items()
            for setup, episodes in task.setups.items()
        ]

    @classmethod
    def describe(
        cls,
        renderer: str = "auto",
        shader: str = "official",
        success_rule: str = "final_step",
        rotation: str = "axis_angle",
        binarize_gripper: bool = False,
        **_: Any,
    ) -> EnvIO:
        return EnvIO(
            cameras=cls.cameras,
            image_size=640,
            state_dim=cls.state_dim,
            action_dim=cls.action_dim,
            camera_aliases={"image": ("overhead_camera", "3rd_view_camera", "primary")},
            protocol={
                "name": "simpler",
                "episodes": "official script grids (simpler_protocol), a fresh env per episode, "
                "env main seed 2022 (the run's seed does not enter)",
                "success_rule": f"{success_rule}: {sp.SUCCESS_RULES[success_rule]}",
                "shader": shader,
                "renderer": renderer,
                "actions": f"7-d, rotation {rotation}, Google gripper relative (+ closes), "
                f"WidowX absolute (+1 open){', binarized' if binarize_gripper else ''}",
                "image": "overhead_camera 512x640 (Google) / 3rd_view_camera 480x640 (WidowX)",
            },
        )

    @classmethod
    def check_runtime(cls, **params: Any) -> None:
        """In the env server: the checkout, the packages, and a renderer that starts."""
        p = cls._checked(params)
        checkout(p["maniskill2_real2sim"])
        if vk.resolve(p["renderer"], p["vulkan_cpu"]) == "lavapipe":
            vk.configure(p["vulkan_cpu"])  # before sapien: it links to libvulkan
        missing = []
        for module in ("sapien.core", "gymnasium", "transforms3d", "cv2", "scipy"):
            try:
                __import__(module)
            except ImportError as exc:
                if "libvulkan" in str(exc):  # installed, but no Vulkan loader on this machine
                    raise ValueError(
                        f"SAPIEN cannot load Vulkan here ({exc}): install a GPU's Vulkan driver "
                        f"(libvulkan1), or use lavapipe: env.params.renderer=lavapipe or auto "
                        f"after {vk.SETUP_HINT}"
                    ) from None
                missing.append(module.partition(".")[0])
        if missing:
            raise ValueError(
                f"the SIMPLER env needs {missing} in Python {sys.version.split()[0]} "
                f"({sys.executable}), which lacks them: {SETUP_HINT}"
            )
        try:
            import sapien.core as sapien

            sapien.SapienRenderer(offscreen_only=True)
        except Exception as exc:
            raise ValueError(
                f"SAPIEN's Vulkan renderer does not start here ({exc}): on a GPU install its "
                f"Vulkan driver; without one set env.params.renderer=lavapipe ({vk.SETUP_HINT})"
            ) from None

    @classmethod
    def check_tasks(cls, task_ids: Sequence[str], episodes: int, **params: Any) -> None:
        """Before any episode, on the driver: the assets every episode of these tasks needs,
        and ray tracing refused on lavapipe."""
        p = cls._checked(params)
        root = checkout(p["maniskill2_real2sim"])
        need = [ep for task_id in task_ids for ep in episodes_of(task_id)[:episodes]]
        if lost := missing_assets(root / "data", need):
            raise ValueError(
                f"SIMPLER assets missing under {root / 'data'} (tasks {list(task_ids)}): "
                f"{lost}; without them SAPIEN builds the scene without its table or objects and "
                "every episode fails quietly: complete the checkout (these files are >= 4 MiB "
                "in the repository) or choose other tasks"
            )
        shader = p["shader"]
        rt = any(ep.ray_tracing for ep in need) if shader == "official" else shader == "rt"
        if rt and vk.resolve(p["renderer"], p["vulkan_cpu"]) == "lavapipe":
            raise ValueError(f"env.params.shader={shader!r}: {RT_ON_CPU}")

    # -- episodes ----------------------------------------------------------------------------
    def tasks(self) -> list[TaskSpec]:
        return list(self._specs.values())

    def _build(self, ep: sp.Episode, task: sp.SimplerTask) -> Any:
        """The env as the evaluator's ``build_maniskill2_env`` makes it for this episode."""
        import gymnasium as gym
        import mani_skill2_real2sim.envs  # noqa: F401  (registers the envs)

        robot = task.robot
        shader = self.shader if self.shader != "official" else ("rt" if ep.ray_tracing else "ibl")
        kwargs: dict[str, Any] = {"shader_dir": shader} if shader != "ibl" else {}
        kwargs.update(
            obs_mode="rgbd",
            robot=robot.uid,
            sim_freq=robot.sim_freq,
            control_mode=robot.control_mode,
            control_freq=robot.control_freq,
            max_episode_steps=task.max_steps,
            scene_name=ep.scene,
            camera_cfgs={"add_segmentation": True},
            renderer_kwargs={"offscreen_only": True},
        )
        if ep.overlay:
            kwargs["rgb_overlay_path"] = str(self.data / "real_inpainting" / ep.overlay)
            kwargs["rgb_overlay_cameras"] = [robot.camera]
        kwargs.update(dict(ep.build))
        self._shader = shader
        return gym.make(ep.env_id, **kwargs)

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        spec = self._specs.get(task_id)
        if spec is None:
            raise ValueError(
                f"task_id={task_id!r} is not a SIMPLER task; valid: {list(self._specs)}"
            )
        task, _ = split_task_id(task_id)
        episodes = episodes_of(task_id)
        if not 0 <= episode_index < len(episodes):
            raise ValueError(
                f"episode {episode_index}: {task_id} has {len(episodes)} official episodes "
                f"(episodes_per_task <= {len(episodes)})"
            )
        ep = episodes[episode_index]
        if lost := missing_assets(self.data, [ep]):
            raise ValueError(f"{task_id} episode {episode_index}: assets missing: {lost}")
        self._clock = EpisodeClock(self.action_dim)  # a failed reset leaves no episode behind
        self._close_env()
        self._env = self._build(ep, task)
        obs, _ = self._env.reset(options=ep.reset_options())
        self._episode, self._robot = ep, task.robot
        self._clock.start(spec)
        self._success = False
        self._obs = obs
        self._instruction = str(self._env.unwrapped.get_language_instruction())
        return self._observe()

    def step(self, action: np.ndarray) -> EnvObservation:
        a = self._clock.take(action)
        sim = sp.to_sim_action(a, self._robot.family, self.rotation, self.binarize)
        self._obs, _, _, _, info = self._env.step(sim)
        now = bool(info["success"])
        self._success = now if self.success_rule == "final_step" else (self._success or now)
        self._instruction = str(self._env.unwrapped.get_language_instruction())
        return self._observe()

    def _observe(self) -> EnvObservation:
        obs = self._obs
        image = np.ascontiguousarray(obs["image"][self._robot.camera]["rgb"], dtype=np.uint8)
        self._generation += 1
        generation = self._generation

        def current() -> bool:  # the live simulator: valid until the next step or reset
            return self._generation == generation

        state = self._state()
        return EnvObservation(
            images={"image": image},
            state=state,
            privileged=LazyState(lambda: self.privileged(state), current),
            status=self._status(),
        )

    def _status(self) -> EpisodeStatus:
        """Success by the task's rule: at the final step (``final_step``, the episode runs to
        its horizon) or at any step (``any_step``, which ends it)."""
        task = self._clock.task
        assert task is not None and self._episode is not None
        return self._clock.status(
            self._instruction,
            self._success,
            ended=self.success_rule == "any_step" and self._success,
            info=EpisodeInfo(init_state_id=f"{task.task_id}/{self._episode.label()}"),
        )

    def privileged(self, state: np.ndarray) -> dict[str, Any]:
        """Simulator state for scripted controllers in tests (never for learned policies):
        ``state.privileged_state``."""
        return privileged_state(self._env.unwrapped, state)

    def _state(self) -> np.ndarray:
        return robot_state(self._env.unwrapped, self._robot.tcp_link)

    def _close_env(self) -> None:
        env, self._env = self._env, None
        if env is not None:
            env.close()

    def close(self) -> None:
        self._close_env()
        self._clock = EpisodeClock(self.action_dim)

    @property
    def control_hz(self) -> float:
        return float(self._robot.control_freq)

    @property
    def render_backend(self) -> str:
        return f"sapien-vulkan-{self.driver}/{self._shader}"
