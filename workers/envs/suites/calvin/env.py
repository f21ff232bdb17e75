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
"""

from __future__ import annotations

import functools
import inspect
import json
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from workers.envs.base import EnvObservation, LazyImages, LazyState, TaskSpec
from workers.io_spec import EnvIO

SUITE = "calvin"
SEQUENCES_FILE = Path(__file__).parent / "data" / "calvin_eval_sequences.json"
EP_LEN = 360  # steps per subtask (evaluate_policy.py)
NUM_SUBTASKS = 5
CAMERAS = {"rgb_static": ("static", 200), "rgb_gripper": ("gripper", 84)}  # key: (calvin, px)
CAMERA_ALIASES = {
    "rgb_static": ("static", "image", "front", "agentview"),
    "rgb_gripper": ("gripper", "wrist", "image2", "wrist_image"),
}
RENDERERS = {"egl": "pybullet-egl", "tiny": "pybullet-tiny"}
# calvin_env commit that mees/calvin's submodule pins (since 2023-05) and that leaves the LED on
# when its button is pressed once at the start of a sequence (fixed in 797142c)
BUTTON_BUG_COMMIT = "1431a46"
SETUP_HINT = (
    "make setup-calvin creates .venv-calvin (Python 3.11 + PyBullet); then set "
    "env.python=.venv-calvin/bin/python"
)
ANNOTATIONS_IN_CALVIN = "calvin_models/conf/annotations/new_playtable_validation.yaml"
TASKS_IN_CALVIN_ENV = "conf/tasks/new_playtable_tasks.yaml"

# the official neutral robot pose (tcp pos, euler, gripper width, 7 joints, gripper action)
NEUTRAL_ROBOT_OBS = np.array(
    [
        *(0.02586889, -0.2313129, 0.5712808, 3.09045411, -0.02908596, 1.50013585, 0.07999963),
        *(-1.21779124, 1.03987629, 2.11978254, -2.34205014, -0.87015899, 1.64119093, 0.55344928),
        1.0,
    ]
)
BLOCK_SLIDER_LEFT = np.array([-2.40851662e-01, 9.24044687e-02, 4.60990009e-01])
BLOCK_SLIDER_RIGHT = np.array([7.03416330e-02, 9.24044687e-02, 4.60990009e-01])
BLOCK_TABLE = (
    np.array([5.00000896e-02, -1.20000177e-01, 4.59990009e-01]),
    np.array([2.29995412e-01, -1.19995140e-01, 4.59990010e-01]),
)
BLOCK_ROT_Z = (np.pi / 2 - np.pi / 8, np.pi / 2 + np.pi / 8)


def fnv1_32(text: str) -> int:
    """The hash the official code seeds scenes with: pyhash's ``fnv1_32()``, which is FNV-1
    (multiply by the FNV prime, then xor) from 0, not from the FNV offset basis, over the
    string's UTF-16-LE bytes. Written here because pyhash does not build on Python >= 3.11."""
    h = 0
    for byte in text.encode("utf-16-le"):
        h = ((h * 0x01000193) & 0xFFFFFFFF) ^ byte
    return h


def condition_seed(condition: dict[str, Any]) -> int:
    """The scene seed of an initial condition: the hash of ``str(dict.values())`` (so the key
    order matters: led, lightbulb, slider, drawer, red_block, blue_block, pink_block, grasped)."""
    return fnv1_32(str(condition.values()))


def initial_state(condition: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(robot_obs 15-d, scene_obs 24-d) of an initial condition, as the official
    ``get_env_state_for_initial_condition`` (numpy's legacy MT19937 stream, same draws)."""
    rng = np.random.RandomState(condition_seed(condition))
    table = list(BLOCK_TABLE)
    rng.shuffle(table)
    on_slider = {"slider_left": BLOCK_SLIDER_LEFT, "slider_right": BLOCK_SLIDER_RIGHT}
    scene = np.zeros(24)
    if condition["slider"] == "left":
        scene[0] = 0.28
    if condition["drawer"] == "open":
        scene[1] = 0.22
    if condition["lightbulb"] == 1:
        scene[3] = 0.088
    scene[4] = condition["lightbulb"]
    scene[5] = condition["led"]
    scene[6:9] = on_slider.get(condition["red_block"], table[0])
    scene[11] = rng.uniform(*BLOCK_ROT_Z)
    if condition["blue_block"] in on_slider:
        scene[12:15] = on_slider[condition["blue_block"]]
    else:
        scene[12:15] = table[1] if condition["red_block"] == "table" else table[0]
    scene[17] = rng.uniform(*BLOCK_ROT_Z)
    scene[18:21] = on_slider.get(condition["pink_block"], table[1])
    scene[23] = rng.uniform(*BLOCK_ROT_Z)
    return NEUTRAL_ROBOT_OBS.copy(), scene


@functools.lru_cache(maxsize=4)
def load_sequences(path: str | None = None) -> tuple[tuple[dict[str, Any], tuple[str, ...]], ...]:
    """The evaluation sequences: (initial condition, five subtask names), in the official order."""
    data = json.loads(Path(path or SEQUENCES_FILE).read_text())
    return tuple((dict(cond), tuple(tasks)) for cond, tasks in data)


def binarize_gripper(action: np.ndarray) -> np.ndarray:
    """A fresh float64 7-vector with the gripper at +1 (open) where > 0, else -1 (close), as the
    official CalvinEnvWrapper; fresh because an older calvin_env scales the array in place."""
    out = np.array(action, dtype=np.float64, copy=True)
    out[6] = 1.0 if out[6] > 0 else -1.0
    return out


def _checkout(calvin_env: str | None) -> Path:
    root = calvin_env or os.environ.get("CALVIN_ENV")
    if not root:
        raise ValueError(
            "env.params.calvin_env is not set and neither is $CALVIN_ENV: point either at a "
            "checkout of calvin_env (MIT, github.com/mees/calvin_env; as a submodule of "
            "`git clone --recurse-submodules https://github.com/mees/calvin`)"
        )
    path = Path(root).expanduser().resolve()
    if not (path / "calvin_env" / "envs" / "play_table_env.py").is_file():
        raise ValueError(
            f"env.params.calvin_env={root}: not a calvin_env checkout (no calvin_env/envs/"
            "play_table_env.py); point it at the calvin_env folder of a mees/calvin clone"
        )
    return path


def _annotations_file(checkout: Path, annotations: str | None) -> Path:
    if annotations is not None:
        path = Path(annotations).expanduser()
        if not path.is_file():
            raise ValueError(f"env.params.annotations={annotations}: no such file")
        return path
    candidates = [checkout.parent / ANNOTATIONS_IN_CALVIN]
    if os.environ.get("CALVIN_ROOT"):
        candidates.insert(0, Path(os.environ["CALVIN_ROOT"]) / ANNOTATIONS_IN_CALVIN)
    for path in candidates:
        if path.is_file():
            return path
    raise ValueError(
        f"the language annotations of the evaluation ({ANNOTATIONS_IN_CALVIN}) are not in the "
        f"mees/calvin checkout around {checkout}: set env.params.annotations to that file, or "
        "$CALVIN_ROOT to the mees/calvin clone"
    )


def checkout_commit(checkout: Path) -> str | None:
    """The checkout's git commit, or None (not a git clone, or no git)."""
    try:
        out = subprocess.run(
            ["git", "-C", str(checkout), "rev-parse", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
        )
    except (OSError, subprocess.TimeoutExpired):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


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
        calvin_env: str | None = None,
        annotations: str | None = None,
        scene: str = "calvin_scene_D",
        cameras: Sequence[str] = ("rgb_static", "rgb_gripper"),
        renderer: str = "egl",
        robot: str = "panda_longer_finger",
        subtask_steps: int = EP_LEN,
        sequences: str | None = None,
    ) -> None:
        params = self._check_params(calvin_env, scene, cameras, renderer, robot, subtask_steps)
        self.checkout = params["checkout"]
        self.cameras = tuple(cameras)
        self.renderer = renderer
        self.render_backend = RENDERERS[renderer]
        self.subtask_steps = subtask_steps
        self.scene = scene
        self._sequences = load_sequences(sequences)
        self._annotations = self._load_annotations(_annotations_file(self.checkout, annotations))
        self._task = self._task_spec(scene, subtask_steps, len(self._sequences))
        self.robot = robot
        self._env = self._build()
        self._oracle = self._build_oracle()
        self._used = False  # the simulator has run a sequence: the next one gets a new one
        self._subtasks: tuple[str, ...] = ()
        self._done_count = 0
        self._steps = 0
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
        checkout = _checkout(calvin_env)
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
        _annotations_file(checked["checkout"], p["annotations"])
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
        """calvin_env's PlayTableSimEnv, composed from its own conf/ as the dataset's
        merged_config.yaml was, and instantiated as the official ``get_env`` does."""
        if str(self.checkout) not in sys.path:
            sys.path.insert(0, str(self.checkout))
        import calvin_env.envs.play_table_env as play_table_env
        import hydra
        from hydra.core.global_hydra import GlobalHydra

        original = play_table_env.get_git_commit_hash
        if not getattr(original, "idr_wrapped", False):

            def commit_or_unknown(path: Any) -> str:  # it raises outside a git clone
                try:
                    return original(path)
                except Exception:
                    return "unknown"

            commit_or_unknown.idr_wrapped = True  # type: ignore[attr-defined]
            play_table_env.get_git_commit_hash = commit_or_unknown
        overrides = [
            "hydra/job_logging=default",  # its colorlog needs a plugin the eval does not
            "hydra/hydra_logging=default",
            "cameras=static_and_gripper",
            f"scene={self.scene}",
            f"robot={self.robot}",
            "use_vr=false",
            f"env.use_egl={str(self.renderer == 'egl').lower()}",
            "env.show_gui=false",
            "env.use_scene_info=true",
        ]
        GlobalHydra.instance().clear()
        with hydra.initialize_config_dir(config_dir=str(self.checkout / "conf"), version_base=None):
            cfg = hydra.compose(config_name="config_data_collection", overrides=overrides)
        try:  # as the official get_env instantiates the dataset's merged config
            env = hydra.utils.instantiate(
                cfg.env, show_gui=False, use_vr=False, use_scene_info=True
            )
        except SystemExit:  # calvin_env exits when the EGL plugin does not load
            raise RuntimeError(
                "PyBullet's EGL renderer plugin did not load here: install an EGL driver (a GPU's, "
                "or Mesa's libegl1), or set env.params.renderer=tiny (CPU renderer, other pixels)"
            ) from None
        self._calvin_cameras = {f"rgb_{cam.name}": cam for cam in env.cameras}
        return env

    def _build_oracle(self) -> Any:
        import hydra
        from omegaconf import OmegaConf

        return hydra.utils.instantiate(OmegaConf.load(self.checkout / TASKS_IN_CALVIN_ENV))

    def _rebuild(self) -> None:
        """A new simulator in this process: the old one disconnected here, once (calvin_env's
        ``__del__`` would disconnect its client id again, which pybullet gives the new one)."""
        old, self._env = self._env, None
        old.close()
        old.ownsPhysicsClient = False
        self._env = self._build()  # client 0 again, as its robot base needs

    @staticmethod
    def _load_annotations(path: Path) -> dict[str, str]:
        from omegaconf import OmegaConf

        return {task: str(texts[0]) for task, texts in OmegaConf.load(path).items()}

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
        self._done_count, self._steps, self._subtask_step, self._failed = 0, 0, 0, None
        self._start_info = env.get_info()
        return self._observe()

    def step(self, action: np.ndarray) -> EnvObservation:
        action = np.asarray(action)
        if action.shape != (self.action_dim,):
            raise ValueError(f"action must have shape ({self.action_dim},), got {action.shape}")
        if self.done:
            raise RuntimeError("step() after the episode is done; call reset()")
        env = self._env
        # env.step without its camera rendering: images are rendered when read (the same
        # pixels: rendering does not touch the physics)
        env.robot.apply_action(binarize_gripper(action))
        for _ in range(env.action_repeat):
            env.p.stepSimulation(physicsClientId=env.cid)
        env.scene.step()
        info = env.get_info()
        self._steps += 1
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
    @property
    def task(self) -> TaskSpec:
        return self._task

    @property
    def subtasks(self) -> tuple[str, ...]:
        return self._subtasks

    @property
    def instruction(self) -> str:
        if not self._subtasks:
            raise RuntimeError("no sequence: call reset() first")
        return self._annotations[self._subtasks[min(self._done_count, NUM_SUBTASKS - 1)]]

    @property
    def success(self) -> bool:
        return self._done_count == NUM_SUBTASKS

    @property
    def done(self) -> bool:
        return self.success or self._failed is not None

    @property
    def subtasks_done(self) -> int:
        return self._done_count

    @property
    def steps(self) -> int:
        return self._steps

    @property
    def init_state_id(self) -> str:
        condition, _ = self._sequences[self._episode]
        return f"sequence {self._episode} (scene seed {condition_seed(condition)})"

    @property
    def failure_cause(self) -> str | None:
        return "subtask_budget" if self._failed else None

    @property
    def failure_reason(self) -> str | None:
        return self._failed

    def close(self) -> None:
        """The physics client is disconnected once, here; calvin_env's own ``__del__`` would
        disconnect by client id again (and kill a later env with the reused id), so it is
        told it no longer owns one."""
        env, self._env = getattr(self, "_env", None), None
        if env is not None:
            env.close()
            env.ownsPhysicsClient = False
