"""The robosuite scene behind the ``tabletop`` suite: a Panda, colored cubes and a bin.

Kept apart from the task logic (``tabletop.py``) so that the robosuite specifics live in one
place. Robosuite builds the MJCF model and runs the OSC_POSE controller at 20 Hz; cube
positions come from our own seeded RNG (``place_cubes``), not robosuite's samplers, so every
cell of a grid sees identical scenes. Images are rendered with ``mujoco.Renderer`` on the same
model with a fast look (no MSAA, reflections or skybox): about 3x cheaper than robosuite's
own camera path on OSMesa, and the tiny VLA is trained on exactly this look. The same
renderer makes the object-hidden images (``FastRenderer.render_without``, the env's
``object_hidden_images``): the chosen objects' geoms left out of one render.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np
import robosuite
from robosuite.environments.manipulation.single_arm_env import SingleArmEnv
from robosuite.models.arenas import TableArena
from robosuite.models.objects import BoxObject
from robosuite.models.tasks import ManipulationTask
from robosuite.utils.mjcf_utils import array_to_string

from workers.envs.suites.tabletop.layout import (
    BIN_CENTER,
    BIN_INNER_HALF,
    BIN_WALL,
    COLORS,
    CUBE_HALF,
    TABLE_TOP_Z,
)


class TabletopScene(SingleArmEnv):
    """Panda at a table with ``colors`` cubes (free) and, optionally, a bin (fixed)."""

    def __init__(
        self, colors: tuple[str, ...], with_bin: bool, n_distractors: int = 0, **kwargs: object
    ) -> None:
        self.colors = colors
        self.with_bin = with_bin
        self.n_distractors = n_distractors  # grey cubes (the distractors perturbation)
        self._pending_distractor_xy: np.ndarray | None = None
        self.table_full_size = (0.8, 0.8, 0.05)
        self.table_offset = np.array((0.0, 0.0, TABLE_TOP_Z))
        self._pending_cube_xy: np.ndarray | None = None
        super().__init__(**kwargs)

    # -- model -----------------------------------------------------------------------------
    def _load_model(self) -> None:
        super()._load_model()
        robot = self.robots[0].robot_model
        robot.set_base_xpos(robot.base_xpos_offset["table"](self.table_full_size[0]))
        arena = TableArena(table_full_size=self.table_full_size, table_offset=self.table_offset)
        arena.set_origin([0, 0, 0])
        # closer than robosuite's agentview, looking down at the workspace and the bin
        arena.set_camera("agentview", pos=[0.45, 0.04, 1.35], quat=[0.6686, 0.2302, 0.2302, 0.6686])
        self.cubes = [
            BoxObject(name=f"cube_{c}", size=[CUBE_HALF] * 3, rgba=list(COLORS[c]), density=200)
            for c in self.colors
        ]
        self.distractors = [
            BoxObject(
                name=f"distractor_{i}", size=[CUBE_HALF] * 3, rgba=[0.6, 0.6, 0.6, 1.0], density=200
            )
            for i in range(self.n_distractors)
        ]
        self.bin_parts = self._bin_parts() if self.with_bin else []
        objects: list = [*self.cubes, *self.distractors, *self.bin_parts]
        self.model = ManipulationTask(
            mujoco_arena=arena, mujoco_robots=[robot], mujoco_objects=objects
        )

    def _bin_parts(self) -> list[BoxObject]:
        """A low open box from five fixed boxes (floor and four walls)."""
        z0 = TABLE_TOP_Z
        t, h = BIN_WALL
        w = BIN_INNER_HALF + t
        grey = [0.45, 0.35, 0.25, 1.0]
        specs = {
            "bin_floor": ([w, w, 0.004], [0, 0, z0 + 0.004]),
            "bin_wall_n": ([w, t, h], [0, BIN_INNER_HALF + t, z0 + h]),
            "bin_wall_s": ([w, t, h], [0, -BIN_INNER_HALF - t, z0 + h]),
            "bin_wall_e": ([t, BIN_INNER_HALF, h], [BIN_INNER_HALF + t, 0, z0 + h]),
            "bin_wall_w": ([t, BIN_INNER_HALF, h], [-BIN_INNER_HALF - t, 0, z0 + h]),
        }
        parts = []
        for name, (size, offset) in specs.items():
            box = BoxObject(name=name, size=size, rgba=grey, joints=None)
            pos = np.array(offset, dtype=float)
            pos[:2] += BIN_CENTER
            box.get_obj().set("pos", array_to_string(pos))
            parts.append(box)
        return parts

    def _setup_references(self) -> None:
        super()._setup_references()
        self.cube_body_ids = [self.sim.model.body_name2id(c.root_body) for c in self.cubes]
        self.bin_body_ids = [self.sim.model.body_name2id(p.root_body) for p in self.bin_parts]

    # -- placement -----------------------------------------------------------------------
    def place_cubes(self, xy: np.ndarray, distractor_xy: np.ndarray | None = None) -> None:
        """Positions for the next reset (one (x, y) per cube, and per distractor), resting on
        the table."""
        self._pending_cube_xy = np.asarray(xy, dtype=float)
        self._pending_distractor_xy = distractor_xy

    def _reset_internal(self) -> None:
        super()._reset_internal()
        # robosuite's Panda gripper integrates its command (current_action += speed * sign(a))
        # and only a hard reset rebuilds it: without this, an episode's first gripper motions
        # depend on how the previous episode on the same scene ended (up to 1.7 cm of drift)
        gripper = self.robots[0].gripper
        gripper.current_action = np.zeros_like(gripper.current_action)
        xy = self._pending_cube_xy
        if xy is None:  # robosuite resets once while constructing: a neutral row of cubes
            xy = np.stack(
                [np.full(len(self.cubes), -0.1), np.linspace(-0.25, 0.05, len(self.cubes))], 1
            )
        dxy = self._pending_distractor_xy
        if self.distractors and dxy is None:  # while constructing: out of the way, in a row
            dxy = np.stack(
                [
                    np.full(len(self.distractors), 0.3),
                    np.linspace(-0.3, 0.3, len(self.distractors)),
                ],
                1,
            )
        cubes = [*self.cubes, *self.distractors]
        xys = [*xy, *(dxy if self.distractors else [])]
        for cube, (x, y) in zip(cubes, xys, strict=True):
            qpos = np.array([x, y, TABLE_TOP_Z + CUBE_HALF + 0.001, 1.0, 0.0, 0.0, 0.0])
            self.sim.data.set_joint_qpos(cube.joints[0], qpos)

    # -- queries -------------------------------------------------------------------------
    def cube_positions(self) -> np.ndarray:
        return np.array([self.sim.data.body_xpos[i] for i in self.cube_body_ids])

    def object_geoms(self, cubes: Iterable[int], with_bin: bool = False) -> tuple[int, ...]:
        """Ids of every geom of the cubes ``cubes`` (indices into ``colors``) and, with
        ``with_bin``, of the bin's five parts: each object's collision geom (group 0, drawn by
        the default render options) and its visual one (group 1), and any geom of a body under
        its root body."""
        m = self.sim.model._model
        roots = {self.cube_body_ids[i] for i in cubes}
        if with_bin:
            roots |= set(self.bin_body_ids)
        return tuple(g for g in range(m.ngeom) if int(m.body_rootid[m.geom_bodyid[g]]) in roots)

    def is_grasped(self, index: int) -> bool:
        return bool(
            self._check_grasp(gripper=self.robots[0].gripper, object_geoms=self.cubes[index])
        )

    def reward(self, action: np.ndarray | None = None) -> float:
        return 0.0  # success is decided by the task layer

    def _check_success(self) -> bool:
        return False


def make_scene(colors: tuple[str, ...], with_bin: bool, n_distractors: int = 0) -> TabletopScene:
    """A scene with OSC_POSE control at 20 Hz and no robosuite rendering (we render ourselves)."""
    return TabletopScene(
        colors=colors,
        with_bin=with_bin,
        n_distractors=n_distractors,
        robots="Panda",
        controller_configs=robosuite.load_controller_config(default_controller="OSC_POSE"),
        gripper_types="default",
        initialization_noise=None,  # deterministic robot start; variety comes from the cubes
        use_camera_obs=False,
        has_renderer=False,
        has_offscreen_renderer=False,
        control_freq=20,
        horizon=100_000,
        ignore_done=True,
        hard_reset=False,
    )


class FastRenderer:
    """mujoco.Renderer per camera with MSAA, reflections and the skybox turned off."""

    def __init__(
        self, scene: TabletopScene, cameras: dict[str, str], size: int, fast: bool = True
    ) -> None:
        import mujoco

        self.model = scene.sim.model._model
        self.data = scene.sim.data._data
        self.cameras = cameras  # our name -> MuJoCo camera name
        if fast:
            self.model.vis.quality.offsamples = 0
        self.renderer = mujoco.Renderer(self.model, size, size)
        if fast:
            flags = self.renderer.scene.flags
            flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            flags[mujoco.mjtRndFlag.mjRND_SKYBOX] = 0
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0

    def render_one(self, name: str) -> np.ndarray:
        self.renderer.update_scene(self.data, camera=self.cameras[name])
        return self.renderer.render().copy()

    def render(self) -> dict[str, np.ndarray]:
        return {name: self.render_one(name) for name in self.cameras}

    def render_without(self, geoms: Sequence[int]) -> dict[str, np.ndarray]:
        """Every camera's image of the current state with ``geoms`` left out (alpha 0 for
        this render only: ``workers.envs.mujoco.scene_edits.geoms_hidden``), from the same
        renderer and look as ``render_one``: the same pixels wherever they do not show them."""
        from workers.envs.mujoco.scene_edits import geoms_hidden

        with geoms_hidden(self.model, geoms):
            return self.render()

    def close(self) -> None:
        self.renderer.close()
