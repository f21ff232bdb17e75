"""LIBERO (hf-libero) as an Env: the four 10-task suites in one env, under a named protocol.

Task ids are ``"<suite>/<index>"`` (``libero_spatial/0`` .. ``libero_10/9``), the index being the
position in the suite's default task order. ``protocol`` (``openpi``, the default, or
``lerobot``; see ``workers.envs.suites.libero.protocol``) pins the seed rule, max steps, no-ops, render
size, replan rule and state arithmetic; the params below override single figures of it:

- ``reset(task_id, episode_index, seed)``: seed the env (``seed``, or ``seed + episode_index``
  under ``lerobot``), reset it, set the suite's fixed init state ``episode_index % n_init_states``,
  then run ``num_noops`` no-op actions ``[0, 0, 0, 0, 0, 0, -1]`` so objects settle; the no-ops
  do not count as steps.
- Episode ends at success (LIBERO's own goal check) or after the suite's max steps.
- Images rendered at ``image_size`` px and flipped 180 degrees (both axes): robosuite renders
  with OpenGL's bottom-up rows, and policies trained on openpi / OFT / lerobot data see the
  flipped view. Rendered lazily by default (``lazy_render``): a camera costs ~110-170 ms per
  render on OSMesa and open-loop chunk steps read no image, so a camera is rendered only when
  its image is read, with the same pixels robosuite's camera observables give (see
  ``LiberoEnv.__init__``).
- State (8,): end-effector position (3), end-effector orientation as axis-angle (3),
  gripper finger positions (2). Action (7,): OSC_POSE deltas (6) + gripper (-1 open, +1 close).

One simulator (``OffScreenRenderEnv``, 5-20 s to build) is kept for the current task and reused
across its episodes; switching task closes it and builds the next. ``suite_tasks`` lists tasks
from LIBERO's benchmark tables without importing MuJoCo; ``describe`` says what the env gives a
policy (for the pre-flight check against a checkpoint). Beside this module: ``protocol`` (the
named conventions), ``tables`` (LIBERO's task tables and init states), ``snapshots`` (lazy
rendering), ``assets`` (LIBERO's config and assets, prepared once).
"""

from __future__ import annotations

import functools
import os
from collections.abc import Mapping, Sequence
from typing import Annotated, Any

import numpy as np

from workers.envs.base import EnvObservation, EpisodeInfo, EpisodeStatus, LazyImages, TaskSpec
from workers.envs.episode_clock import EpisodeClock
from workers.envs.mujoco.stability import mujoco_instability, raise_if_unstable
from workers.envs.suites.libero import tables as hf_libero_tables
from workers.envs.suites.libero.assets import LiberoSetupError
from workers.envs.suites.libero.protocol import (
    CAMERAS,
    PROTOCOLS,
    SUITES,
    SUPPORTED_SUITES,
    LiberoProtocol,
    quat_to_axis_angle,
    state_vector,
)
from workers.envs.suites.libero.snapshots import Frame, Snapshots, install_snapshot, render_frame
from workers.io_spec import ROBOSUITE_CAMERA_ALIASES, EnvIO
from workers.param_doc import Doc

__all__ = [
    "CAMERAS",
    "PROTOCOLS",
    "SUITES",
    "SUPPORTED_SUITES",
    "LiberoEnv",
    "LiberoProtocol",
    "quat_to_axis_angle",
    "state_vector",
]

NOOP_ACTION: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.0)


def _table_geoms(model: Any) -> list[str | int]:
    """The geoms ``table_color`` tints: the visible (group 1) geoms of the scene's table, named
    by the geom or its body (``table_visual`` and legs; the living room's unnamed mesh on
    ``living_room_table_col``), else the floor (LIBERO-Object's scenes have no table)."""
    import mujoco

    def name(kind: Any, i: int) -> str:
        return mujoco.mj_id2name(model, kind, i) or ""

    table: list[str | int] = [
        g
        for g in range(model.ngeom)
        if model.geom_group[g] == 1
        and "table"
        in name(mujoco.mjtObj.mjOBJ_GEOM, g)
        + name(mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[g]))
    ]
    return table or ["floor"]


class LiberoEnv:
    """The LIBERO suites behind the Env protocol (see the module docstring for the protocol)."""

    suite = "libero"
    action_dim = 7
    state_dim = 8
    gripper_index = 6  # -1 open, +1 close
    #: scene perturbations this suite applies (workers/envs/wrappers/perturbations.py): the main
    #: camera is ``agentview``; ``table_color`` tints the table (the floor in scenes without,
    #: see ``_table_geoms``)
    perturbation_kinds = ("camera_shift", "camera_pitch", "light_dim", "table_color", "init_jitter")
    #: where the suites' tables come from: a module with ``list_tasks(protocol)``,
    #: ``benchmark_suite(name)``, ``fixed_init_states(bench, index)`` and ``check_assets()``
    #: (hf-libero's here; LIBERO-PRO's for the ``libero_pro`` suite), the suite names it knows
    #: and the suite whose protocol figures each takes
    tables: Any = hf_libero_tables
    known_suites: tuple[str, ...] = SUPPORTED_SUITES

    @staticmethod
    def base_suite(suite: str) -> str:
        return suite

    def __init__(
        self,
        protocol: Annotated[
            str,
            Doc(
                "the evaluation convention: openpi (the paper's tables) or lerobot (lerobot-eval's)"
            ),
        ] = "openpi",
        suites: Annotated[Sequence[str], Doc("the LIBERO suites whose tasks the env has")] = SUITES,
        image_size: Annotated[
            int | None,
            Doc("render px per side; None: the protocol's (openpi 256, lerobot the checkpoint's)"),
        ] = None,
        cameras: Annotated[
            Sequence[str], Doc("the cameras rendered: agentview, wrist; () renders nothing")
        ] = ("agentview", "wrist"),
        num_noops: Annotated[
            int | None, Doc("uncounted no-op steps after each reset; None: the protocol's (10)")
        ] = None,
        max_steps: Annotated[
            Mapping[str, int] | None,
            Doc("suite -> control steps per episode; None: the protocol's"),
        ] = None,
        flip_images: Annotated[
            bool, Doc("flip images 180 degrees, as LIBERO's policies were trained")
        ] = True,
        control_hz: Annotated[float, Doc("control steps per simulated second")] = 20.0,
        lazy_render: Annotated[
            bool, Doc("render a camera only when its image is read (the same pixels)")
        ] = True,
    ) -> None:
        """``protocol`` names the evaluation convention (``openpi`` or ``lerobot``); the other
        params left at None take its figures, and given ones override them (logged with the
        run): ``max_steps`` maps suite -> steps per suite, ``image_size`` None renders at the
        protocol's size (``lerobot``: the checkpoint's, filled in by the driver's pre-flight;
        360 without a checkpoint). ``cameras=()`` renders nothing (state-only observations: for
        physics benchmarks; ``check_env`` requires at least one camera). The env's random seed
        comes from ``reset``'s ``seed`` by the protocol's rule.

        ``lazy_render`` (default): observations carry ``LazyImages``; a camera is rendered when
        its image is first read, so reset (its no-ops included) and steps whose images nobody
        reads render nothing. The pixels equal the eager path's (tested with ``array_equal``):
        robosuite samples its observables at a substep inside the control step, not after the
        last one, so rendering the final state would show a different arm pose. Instead the
        simulator is built without camera observables, ``MjData`` is copied (<1 ms) each time
        robosuite samples ``snapshots.SNAPSHOT_OBSERVABLE``, and a read renders that copy with
        the call the camera sensor makes (``sim.render``, same context, MSAA, lights, size and
        ``macros.IMAGE_CONVENTION``). Images must be read before the next ``reset`` or
        ``close`` (RuntimeError after). ``lazy_render=False``: robosuite renders every camera
        on every step and on reset (its camera observables), as before."""
        self.protocol = LiberoProtocol.from_params(
            protocol,
            suites,
            image_size,
            cameras,
            num_noops,
            max_steps,
            flip_images,
            control_hz,
            self.known_suites,
            self.base_suite,
        )
        self.lazy_render = bool(lazy_render)
        self._snapshots = Snapshots()
        self.cameras = self.protocol.cameras
        self.control_hz = self.protocol.control_hz
        self._specs = {t.task_id: t for t in self.tables.list_tasks(self.protocol)}
        self._sim: Any = None  # OffScreenRenderEnv of self._sim_task
        self._sim_task: str | None = None
        self._init_states: np.ndarray | None = None
        self._clock = EpisodeClock(self.action_dim)
        self._init_index = 0
        self._perturbation: Any = None  # for the next reset (set_perturbation)
        self._perturber: Any = None  # MujocoScenePerturber of the model last perturbed
        self._init_suffix = ""  # the layout perturbation, in init_state_id
        self._success = False

    @classmethod
    def _protocol_of(cls, params: dict[str, Any]) -> LiberoProtocol:
        """The validated protocol of constructor params (``lazy_render`` changes nothing): the
        params bind to the class's own constructor (a name it does not take raises TypeError),
        and LiberoEnv's parameters decide the protocol."""
        import inspect

        inspect.signature(cls.__init__).bind(None, **params)
        sig = inspect.signature(LiberoEnv.__init__)
        bound = sig.bind(None, **{k: v for k, v in params.items() if k in sig.parameters})
        bound.apply_defaults()
        args = dict(bound.arguments)
        for name in ("self", "lazy_render"):
            args.pop(name)
        return LiberoProtocol.from_params(**args, known=cls.known_suites, base_of=cls.base_suite)

    @classmethod
    def suite_tasks(cls, **params: Any) -> list[TaskSpec]:
        """The tasks these constructor params give, from LIBERO's tables: no simulator, no
        MuJoCo import."""
        return cls.tables.list_tasks(cls._protocol_of(params))

    @classmethod
    def describe(cls, **params: Any) -> EnvIO:
        """What an env of these params gives a policy, with its protocol (no simulator)."""
        p = cls._protocol_of(params)
        return EnvIO(
            cameras=p.cameras,
            image_size=p.image_size,
            state_dim=cls.state_dim,
            action_dim=cls.action_dim,
            camera_aliases={c: ROBOSUITE_CAMERA_ALIASES[c] for c in p.cameras},
            image_size_from_checkpoint=p.image_size_from_checkpoint,
            replan=p.replan,
            protocol=p.record(),
        )

    def tasks(self) -> list[TaskSpec]:
        return list(self._specs.values())

    # -- simulator lifecycle -------------------------------------------------------------

    def _spec(self, task_id: str) -> TaskSpec:
        spec = self._specs.get(task_id)
        if spec is None:
            raise ValueError(f"task_id={task_id!r} unknown; valid: {list(self._specs)}")
        return spec

    def _open(self, spec: TaskSpec) -> None:
        """Make the simulator of ``spec`` current, reusing it when it already is."""
        if self._sim is not None and self._sim_task == spec.task_id:
            return
        self._close_sim()
        suite, index = spec.suite, int(spec.task_id.rsplit("/", 1)[1])
        bench = self.tables.benchmark_suite(suite)
        self._init_states = self.tables.fixed_init_states(bench, index)
        self._sim = self._make_sim(bench.get_task_bddl_file_path(index), spec.max_steps)
        self._sim_task = spec.task_id

    def _make_sim(self, bddl_file: str, max_steps: int) -> Any:
        from workers.rendering import configure_rendering

        configure_rendering()  # before robosuite/MuJoCo are imported (no-op if already chosen)
        self.tables.check_assets()
        from libero.libero.envs import OffScreenRenderEnv

        p = self.protocol
        if not os.path.isfile(bddl_file):
            raise LiberoSetupError(f"{bddl_file} is missing: reinstall hf-libero")
        lazy = self.lazy_render and bool(p.cameras)
        sim = OffScreenRenderEnv(
            bddl_file_name=bddl_file,
            camera_names=[CAMERAS[c][0] for c in p.cameras],
            camera_heights=p.image_size,
            camera_widths=p.image_size,
            # lazy: no camera observables, so robosuite renders nothing by itself (not on
            # build, reset, no-ops or steps); the offscreen context is made all the same
            use_camera_obs=bool(p.cameras) and not lazy,
            control_freq=p.control_hz,
            # robosuite refuses to step past its horizon (default 1000): make room for the
            # longest episode this protocol allows.
            horizon=max(1000, max_steps + p.num_noops),
        )
        if lazy:
            install_snapshot(sim.env, self._snapshots)
        return sim

    def _close_sim(self) -> None:
        self._snapshots.clear()
        self._perturber = None
        sim, self._sim, self._sim_task = self._sim, None, None
        if sim is not None:
            sim.close()

    def close(self) -> None:
        """Idempotent."""
        self._close_sim()
        self._clock = EpisodeClock(self.action_dim)

    # -- episodes -------------------------------------------------------------------------

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        spec = self._spec(task_id)
        if episode_index < 0:
            raise ValueError(f"episode_index must be >= 0, got {episode_index}")
        self._clock = EpisodeClock(self.action_dim)  # a failed reset leaves no episode behind
        self._open(spec)
        assert self._init_states is not None
        self._init_index = episode_index % len(self._init_states)
        self._sim.seed(self.protocol.reset_seed(seed, episode_index))
        self._sim.reset()
        mujoco_instability(self._sim.env.sim.data._data)  # what an earlier episode left
        p, self._init_suffix = self._perturbation, ""
        self._perturb_scene(p)
        raw = self._sim.set_init_state(self._init_states[self._init_index])
        if p is not None and p.kind == "init_jitter":
            raw = self._jitter(p, task_id, episode_index, seed)
        for _ in range(self.protocol.num_noops):
            raw, _, _, _ = self._sim.step(list(NOOP_ACTION))
        # a scene that diverges while settling is as unscorable as one that diverges later
        raise_if_unstable(
            self._sim.env.sim.data._data,
            f"in the no-ops after reset of {task_id} episode {episode_index}",
        )
        self._clock.start(spec)
        self._success = False
        return self._observe(raw)

    # -- perturbations (workers/envs/wrappers/perturbations.py) ---------------------------------------

    def set_perturbation(self, p: Any) -> None:
        """The scene perturbation of the next reset (None: the unperturbed scene)."""
        if p is not None and p.kind not in self.perturbation_kinds:
            raise ValueError(f"libero cannot apply {p.kind}; it applies {self.perturbation_kinds}")
        self._perturbation = p

    def _perturb_scene(self, p: Any) -> None:
        """Camera, light and table kinds on the model ``reset`` left; before the init state is
        set, whose forward pass places camera and lights. LIBERO's hard reset builds a new
        model each time; a model that outlived a perturbed episode is restored first."""
        model = self._sim.env.sim.model._model
        if self._perturber is not None and self._perturber.model is model:
            self._perturber.restore()
        if p is None or p.kind == "init_jitter":
            return
        if self._perturber is None or self._perturber.model is not model:
            from workers.envs.mujoco.scene_edits import MujocoScenePerturber

            self._perturber = MujocoScenePerturber(
                model, CAMERAS["agentview"][0], _table_geoms(model)
            )
        self._perturber.apply(p, self._sim.env.sim.data._data)

    def _jitter(self, p: Any, task_id: str, episode_index: int, seed: int) -> Any:
        """Every free object (the robot has a fixed base) moved by up to the severity in x and
        y from its fixed init state, seeded; the no-ops that follow let it settle."""
        import mujoco

        from workers.envs.wrappers.perturbation_grammar import join_task

        sim = self._sim.env.sim
        model, qpos = sim.model._model, sim.data._data.qpos
        rng = p.rng(seed, join_task(task_id, p), episode_index)
        for j in range(model.njnt):
            if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                adr = model.jnt_qposadr[j]
                qpos[adr : adr + 2] += rng.uniform(-p.severity, p.severity, 2)
        self._init_suffix = join_task("", p)
        return self._sim.set_init_state(self._sim.get_sim_state())

    def step(self, action: np.ndarray) -> EnvObservation:
        a = self._clock.take(action)
        raw, _, goal_reached, _ = self._sim.step(a)
        # MuJoCo resets a diverged simulation and carries on: an error row, not a failure
        task = self._clock.task
        assert task is not None
        raise_if_unstable(
            self._sim.env.sim.data._data, f"at step {self._clock.steps} of {task.task_id}"
        )
        self._success = bool(goal_reached)  # hf-libero's done is its goal check
        return self._observe(raw)

    def _observe(self, raw: Mapping[str, np.ndarray]) -> EnvObservation:
        images: Mapping[str, np.ndarray]
        if self.lazy_render and self.cameras:
            frame = self._snapshots.latest
            assert frame is not None, "robosuite sampled no observable"
            images = LazyImages(self.cameras, functools.partial(self._render, frame))
        else:
            images = {cam: self._finish(raw[CAMERAS[cam][1]]) for cam in self.cameras}
        return EnvObservation(
            images=images,
            state=state_vector(raw, self.protocol.float32_state),
            status=self._status(),
        )

    def _status(self) -> EpisodeStatus:
        task = self._clock.task
        assert task is not None
        init = f"{task.task_id}/init{self._init_index}{self._init_suffix}"
        return self._clock.status(
            str(task.instruction),
            self._success,
            ended=self._success,
            info=EpisodeInfo(init_state_id=init),
        )

    def _finish(self, img: np.ndarray) -> np.ndarray:
        """An image as robosuite's camera observable gives it -> as observations carry it."""
        return np.ascontiguousarray(img[::-1, ::-1] if self.protocol.flip_images else img)

    def _render(self, frame: Frame, cam: str) -> np.ndarray:
        """``cam`` of ``frame`` as robosuite's camera sensor renders it
        (``snapshots.render_frame``), then ``_finish``."""
        if self._sim is None or frame.sim is not self._sim.env.sim:
            raise RuntimeError(
                f"camera {cam!r}: this observation is from before the last reset() or close(), "
                "and its images were not read in time: its simulator is gone"
            )
        return self._finish(render_frame(frame, CAMERAS[cam][0], self.protocol.image_size))
