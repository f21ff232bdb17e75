"""The ``calvin`` suite: CALVIN's ABC→D evaluation (Mees et al.), as the official code runs it.

What the official ``calvin_models/calvin_agent/evaluation/evaluate_policy.py`` does, and this
adapter with it:

- the env is calvin_env's ``PlayTableSimEnv`` built from calvin_env's own ``conf/`` (the
  dataset's ``validation/.hydra/merged_config.yaml`` is that composition: cameras static +
  gripper, scene D, robot ``panda_longer_finger``); no dataset is needed;
- an episode is one of the official 1000 evaluation sequences (``multistep_sequences.
  get_sequences(1000)``, shipped in ``workers/envs/suites/calvin/data/calvin_eval_sequences.json``; episode
  ``e`` is sequence ``e``): the scene is reset from the sequence's initial condition (robot in
  its neutral pose, blocks placed with numpy's legacy RNG seeded by pyhash's FNV-1 32 of the
  condition), then its five subtasks run in turn, each for at most 360 steps, with the task
  oracle of ``new_playtable_tasks.yaml`` checked after every step against the subtask's start,
  the instruction of ``new_playtable_validation.yaml`` and the policy reset at each subtask;
  the sequence stops at the first failed subtask (Avg Len and the i/5 rates come from the
  chain aggregation);
- observations: ``rgb_static`` 200x200 and ``rgb_gripper`` 84x84 (rendered only when read),
  the 15-d ``robot_obs`` as the state; actions: 7-d relative (position x 0.02 m, orientation
  x 0.05 rad, added to the robot's target pose by calvin_env), the gripper binarized as the
  official wrapper does (> 0: open +1, else close -1).

Deliberate difference: each sequence runs in a freshly built simulator (about 1 s), so its
result does not depend on which sequences ran before it in the same process. The official loop
resets one simulator for all 1000, which carries Bullet's contact, solver, sleeping and
broad-phase state over: measured here, two runs of one sequence with the same actions diverge
from step 2 (up to 1e-2 after 150 steps), also after pybullet's restoreState; sharding episodes
across actors would then change results. A rebuilt simulator gives, to the bit, what a new
process gives.

calvin_env (MIT, GitHub only) and PyBullet (wheels up to Python 3.11) run in an env server
(``env.python``: ``make setup-calvin`` creates ``.venv-calvin``); this module imports only
numpy at load, so the driver lists tasks and checks params without them. The checkout comes
from ``env.params.calvin_env`` or ``$CALVIN_ENV``; the annotations from the mees/calvin
checkout it is a submodule of (or ``env.params.annotations``). Nothing of theirs is copied.

Beside this module: ``sequences`` (the 1000 sequences and the initial scene of each, numpy
only) and ``checkout`` (where calvin_env and the annotations are, and the simulator and task
oracle built from them).
"""

from __future__ import annotations

import inspect
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any

import numpy as np

from workers.envs.base import (
    EnvObservation,
    EpisodeInfo,
    EpisodeStatus,
    LazyImages,
    LazyState,
    TaskSpec,
)
from workers.envs.episode_clock import EpisodeClock
from workers.envs.suites.calvin.checkout import (
    BUTTON_BUG_COMMIT,
    annotations_file,
    build_oracle,
    build_play_table,
    checkout_commit,
    find_checkout,
    load_annotations,
)
from workers.envs.suites.calvin.sequences import (
    EP_LEN,
    NUM_SUBTASKS,
    condition_seed,
    initial_state,
    load_sequences,
)
from workers.io_spec import EnvIO
from workers.param_doc import Doc

SUITE = "calvin"
CAMERAS = {"rgb_static": ("static", 200), "rgb_gripper": ("gripper", 84)}  # key: (calvin, px)
CAMERA_ALIASES = {
    "rgb_static": ("static", "image", "front", "agentview"),
    "rgb_gripper": ("gripper", "wrist", "image2", "wrist_image"),
}
RENDERERS = {"egl": "pybullet-egl", "tiny": "pybullet-tiny"}
SETUP_HINT = (
    "make setup-calvin creates .venv-calvin (Python 3.11 + PyBullet); then set "
    "env.python=.venv-calvin/bin/python"
)


def binarize_gripper(action: np.ndarray) -> np.ndarray:
    """A fresh float64 7-vector with the gripper at +1 (open) where > 0, else -1 (close), as the
    official CalvinEnvWrapper; fresh because an older calvin_env scales the array in place."""
    out = np.array(action, dtype=np.float64, copy=True)
    out[6] = 1.0 if out[6] > 0 else -1.0
    return out


class CalvinEnv:
    """CALVIN's evaluation behind the Env protocol (see the module docstring)."""

    suite = SUITE
    control_hz = 30.0  # bullet 240 Hz, action_repeat 8
    action_dim = 7
    state_dim = 15
    gripper_index = 6
    policy_reset_per_subtask = True
    server_setup_hint = SETUP_HINT

    def __init__(
        self,
        calvin_env: Annotated[str | None, Doc("the calvin_env checkout; None: $CALVIN_ENV")] = None,
        annotations: Annotated[
            str | None,
            Doc(
                "the evaluation's language annotations (yaml); None: those of the mees/calvin clone around calvin_env"
            ),
        ] = None,
        scene: Annotated[str, Doc("the CALVIN scene the sequences run in")] = "calvin_scene_D",
        cameras: Annotated[Sequence[str], Doc("the cameras rendered: rgb_static, rgb_gripper")] = (
            "rgb_static",
            "rgb_gripper",
        ),
        renderer: Annotated[
            str, Doc("egl (as the CALVIN data was rendered) or tiny (PyBullet's CPU renderer)")
        ] = "egl",
        robot: Annotated[str, Doc("the robot of calvin_env's config")] = "panda_longer_finger",
        subtask_steps: Annotated[
            int, Doc("steps each subtask of a chain may take (the official 360)")
        ] = EP_LEN,
        sequences: Annotated[
            str | None, Doc("a file of evaluation sequences; None: the official 1,000")
        ] = None,
    ) -> None:
        params = self._check_params(calvin_env, scene, cameras, renderer, robot, subtask_steps)
        self.checkout = params["checkout"]
        self.cameras = tuple(cameras)
        self.renderer = renderer
        self.render_backend = RENDERERS[renderer]
        self.subtask_steps = subtask_steps
        self.scene = scene
        self._sequences = load_sequences(sequences)
        self._annotations = load_annotations(annotations_file(self.checkout, annotations))
        self._task = self._task_spec(scene, subtask_steps, len(self._sequences))
        self.robot = robot
        self._env = self._build()
        self._oracle = build_oracle(self.checkout)
        self._used = False  # the simulator has run a sequence: the next one gets a new one
        self._subtasks: tuple[str, ...] = ()
        self._done_count = 0
        self._clock = EpisodeClock(self.action_dim)
        self._subtask_step = 0
        self._start_info: dict[str, Any] | None = None
        self._failed: str | None = None
        self._episode = -1
        self._generation = 0

    # -- params, without a simulator ---------------------------------------------------------
    @staticmethod
    def _check_params(
        calvin_env: str | None,
        scene: str,
        cameras: Sequence[str],
        renderer: str,
        robot: str,
        subtask_steps: int,
    ) -> dict[str, Any]:
        checkout = find_checkout(calvin_env)
        conf = checkout / "conf"
        for field, value, folder in (("scene", scene, "scene"), ("robot", robot, "robot")):
            if not (conf / folder / f"{value}.yaml").is_file():
                known = sorted(p.stem for p in (conf / folder).glob("*.yaml"))
                raise ValueError(f"env.params.{field}={value!r} is not in {conf / folder}: {known}")
        unknown = [c for c in cameras if c not in CAMERAS]
        if unknown or not cameras:
            raise ValueError(f"env.params.cameras={list(cameras)}: choose from {list(CAMERAS)}")
        if renderer not in RENDERERS:
            raise ValueError(
                f"env.params.renderer={renderer!r}: 'egl' (PyBullet's EGL plugin, as the CALVIN "
                "data was rendered; Mesa works without a GPU) or 'tiny' (its CPU TinyRenderer: "
                "faster on a CPU, other pixels)"
            )
        if subtask_steps < 1:
            raise ValueError(
                f"env.params.subtask_steps={subtask_steps} must be >= 1 (official 360)"
            )
        return {"checkout": checkout}

    @staticmethod
    def _task_spec(scene: str, subtask_steps: int, n: int) -> TaskSpec:
        letter = scene.removeprefix("calvin_scene_")
        return TaskSpec(
            task_id=f"scene_{letter}",
            name=f"the {n} official 5-subtask evaluation sequences in scene {letter}",
            max_steps=NUM_SUBTASKS * subtask_steps,
            subtasks_total=NUM_SUBTASKS,
            suite=SUITE,
            episodes_total=n,
        )

    @classmethod
    def suite_tasks(
        cls, scene: str = "calvin_scene_D", subtask_steps: int = EP_LEN, **params: Any
    ) -> list[TaskSpec]:
        n = len(load_sequences(params.get("sequences")))
        return [cls._task_spec(scene, subtask_steps, n)]

    @classmethod
    def describe(
        cls,
        cameras: Sequence[str] = ("rgb_static", "rgb_gripper"),
        renderer: str = "egl",
        scene: str = "calvin_scene_D",
        subtask_steps: int = EP_LEN,
        calvin_env: str | None = None,
        **_: Any,
    ) -> EnvIO:
        sizes = {CAMERAS[c][1] for c in cameras if c in CAMERAS}
        protocol: dict[str, object] = {
            "name": "calvin",
            "sequences": "official 1000 (multistep_sequences.get_sequences), episode e = sequence e",
            "subtask_steps": subtask_steps,
            "scene": scene,
            "renderer": RENDERERS.get(renderer, renderer),
            "policy_reset": "per subtask",
            "actions": "relative 7-d (x0.02 m, x0.05 rad), gripper binarized (>0 open)",
            "reset": "a freshly built simulator per sequence (history-free), then the official reset",
        }
        root = calvin_env or os.environ.get("CALVIN_ENV")
        if root and (commit := checkout_commit(Path(root))):
            protocol["calvin_env_commit"] = commit[:12]
            if commit.startswith(BUTTON_BUG_COMMIT):
                protocol["calvin_env_warning"] = (
                    "this commit (what mees/calvin pins) leaves the LED on when its button is "
                    "pressed once: turn_off_led cannot succeed; 797142c fixes it"
                )
        return EnvIO(
            cameras=tuple(cameras),
            image_size=max(sizes) if sizes else 200,
            camera_sizes={c: CAMERAS[c][1] for c in cameras if c in CAMERAS},
            state_dim=cls.state_dim,
            action_dim=cls.action_dim,
            camera_aliases={c: CAMERA_ALIASES[c] for c in cameras if c in CAMERA_ALIASES},
            protocol=protocol,
        )

    @classmethod
    def check_runtime(cls, **params: Any) -> None:
        """What the env needs where it runs: the checkout, the annotations and the packages
        (``params``: the constructor's, defaults filled in from its signature)."""
        bound = inspect.signature(cls).bind(**params)
        bound.apply_defaults()
        p = bound.arguments
        checked = cls._check_params(
            p["calvin_env"], p["scene"], p["cameras"], p["renderer"], p["robot"], p["subtask_steps"]
        )
        annotations_file(checked["checkout"], p["annotations"])
        missing = []
        for module in ("pybullet", "hydra", "omegaconf", "gym", "cv2", "quaternion", "scipy"):
            try:
                __import__(module)
            except ImportError:
                missing.append(module)
        if missing:
            raise ValueError(
                f"the CALVIN env needs {missing} in Python {sys.version.split()[0]} "
                f"({sys.executable}), which lacks them: {SETUP_HINT}"
            )

    # -- the simulator -----------------------------------------------------------------------
    def _build(self) -> Any:
        """A new simulator (see ``checkout.build_play_table``), its cameras by our names."""
        env = build_play_table(self.checkout, self.scene, self.robot, self.renderer)
        self._calvin_cameras = {f"rgb_{cam.name}": cam for cam in env.cameras}
        return env

    def _rebuild(self) -> None:
        """A new simulator in this process: the old one disconnected here, once (calvin_env's
        ``__del__`` would disconnect its client id again, which pybullet gives the new one)."""
        old, self._env = self._env, None
        old.close()
        old.ownsPhysicsClient = False
        self._env = self._build()  # client 0 again, as its robot base needs

    # -- Env protocol ------------------------------------------------------------------------
    def tasks(self) -> list[TaskSpec]:
        return [self._task]

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        if task_id != self._task.task_id:
            raise ValueError(f"task_id={task_id!r} unknown; allowed: [{self._task.task_id!r}]")
        if not 0 <= episode_index < len(self._sequences):
            raise ValueError(
                f"episode {episode_index}: there are {len(self._sequences)} evaluation sequences "
                f"(episodes_per_task <= {len(self._sequences)})"
            )
        condition, self._subtasks = self._sequences[episode_index]
        robot_obs, scene_obs = initial_state(condition)
        if self._used:
            self._rebuild()
        self._used = True
        env = self._env
        env.reset(robot_obs=robot_obs, scene_obs=scene_obs)  # the official reset
        self._episode = episode_index
        self._done_count, self._subtask_step, self._failed = 0, 0, None
        self._clock.start(self._task)
        self._start_info = env.get_info()
        return self._observe()

    def step(self, action: np.ndarray) -> EnvObservation:
        self._clock.take(action)  # checked and counted; the action itself keeps its dtype
        action = np.asarray(action)
        env = self._env
        # env.step without its camera rendering: images are rendered when read (the same
        # pixels: rendering does not touch the physics)
        env.robot.apply_action(binarize_gripper(action))
        for _ in range(env.action_repeat):
            env.p.stepSimulation(physicsClientId=env.cid)
        env.scene.step()
        info = env.get_info()
        self._subtask_step += 1
        subtask = self._subtasks[self._done_count]
        if self._oracle.get_task_info_for_set(self._start_info, info, {subtask}):
            self._done_count += 1
            self._subtask_step = 0
            self._start_info = info  # the next subtask starts here (its rollout's get_info)
        elif self._subtask_step >= self.subtask_steps:
            self._failed = (
                f"subtask {self._done_count + 1}/{NUM_SUBTASKS} {subtask!r} not done within "
                f"{self.subtask_steps} steps"
            )
        return self._observe()

    def _observe(self) -> EnvObservation:
        env = self._env
        state = np.asarray(env.robot.get_observation()[0], dtype=np.float32)
        self._generation += 1
        generation = self._generation

        def current() -> bool:  # the live simulator: valid until the next step or reset
            return self._generation == generation

        def render(camera: str) -> np.ndarray:
            rgb, _ = self._calvin_cameras[camera].render()
            return np.ascontiguousarray(rgb, dtype=np.uint8)

        return EnvObservation(
            images=LazyImages(self.cameras, render, current),
            state=state,
            privileged=LazyState(self.privileged, current),
            status=self._status(),
        )

    def privileged(self) -> dict[str, Any]:
        """Simulator state for scripted controllers in tests (never for learned policies)."""
        env = self._env
        return {
            "scene_obs": np.asarray(env.scene.get_obs(), dtype=np.float64),
            "tcp_pos": np.asarray(env.robot.get_observation()[0][:3], dtype=np.float64),
            "target_pos": np.asarray(env.robot.target_pos, dtype=np.float64),
            "target_orn": np.asarray(env.robot.target_orn, dtype=np.float64),
            "subtask": self._subtasks[min(self._done_count, NUM_SUBTASKS - 1)],
        }

    # -- status ------------------------------------------------------------------------------
    def _status(self) -> EpisodeStatus:
        """The chain's status: success when all five subtasks are done; ended early when one
        is not done within ``subtask_steps`` (CALVIN has no horizon of its own beyond that)."""
        success = self._done_count == NUM_SUBTASKS
        condition, _ = self._sequences[self._episode]
        return self._clock.status(
            self._annotations[self._subtasks[min(self._done_count, NUM_SUBTASKS - 1)]],
            success,
            ended=success or self._failed is not None,
            subtasks_done=self._done_count,
            info=EpisodeInfo(
                init_state_id=f"sequence {self._episode} (scene seed {condition_seed(condition)})",
                failure_cause="subtask_budget" if self._failed else None,
                failure_reason=self._failed,
            ),
        )

    def close(self) -> None:
        """The physics client is disconnected once, here; calvin_env's own ``__del__`` would
        disconnect by client id again (and kill a later env with the reused id), so it is
        told it no longer owns one."""
        env, self._env = getattr(self, "_env", None), None
        if env is not None:
            env.close()
            env.ownsPhysicsClient = False
