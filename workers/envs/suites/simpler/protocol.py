"""SIMPLER's official evaluation protocol as data: robots, episodes, success rules, actions.

Everything here is read off SimplerEnv's evaluation scripts (``scripts/rt1_*.sh``,
``scripts/octo_bridge.sh``), its evaluator (``simpler_env/evaluation/maniskill2_evaluator.py``)
and ManiSkill2_real2sim's task envs, at SimplerEnv 4ab7178 / ManiSkill2_real2sim ef7a4d4;
nothing of theirs is imported or copied. numpy and scipy only: the driver lists tasks and
checks params without SAPIEN. The official episode lists of every task are in ``grids``, what
each episode loads in ``assets``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

GOOGLE_CONTROL = (
    "arm_pd_ee_delta_pose_align_interpolate_by_planner"
    "_gripper_pd_joint_target_delta_pos_interpolate_by_planner"
)
WIDOWX_CONTROL = "arm_pd_ee_target_delta_pose_align2_gripper_pd_joint_pos"
SETUPS = ("visual_matching", "variant_agg")
SUCCESS_RULES = {
    "final_step": "info['success'] of the last step; the episode runs its max steps "
    "(SimplerEnv's evaluator: it ignores the env's done flag)",
    "any_step": "success at any step; the episode ends at the first (not SimplerEnv's rule)",
}


@dataclass(frozen=True)
class Robot:
    """One robot's side of the protocol."""

    uid: str  # ManiSkill2_real2sim's robot
    family: str  # google | widowx: the action convention
    camera: str  # the observation camera SimplerEnv reads (get_image_from_maniskill2_obs_dict)
    height: int
    width: int
    control_freq: int
    sim_freq: int
    control_mode: str
    tcp_link: str  # the end-effector link of its arm controller


GOOGLE = Robot(
    "google_robot_static",
    "google",
    "overhead_camera",
    512,
    640,
    3,
    513,
    GOOGLE_CONTROL,
    "link_gripper_tcp",
)
WIDOWX = Robot(
    "widowx", "widowx", "3rd_view_camera", 480, 640, 5, 500, WIDOWX_CONTROL, "ee_gripper_link"
)
WIDOWX_SINK = Robot(
    "widowx_sink_camera_setup",
    "widowx",
    "3rd_view_camera",
    480,
    640,
    5,
    500,
    WIDOWX_CONTROL,
    "ee_gripper_link",
)


@dataclass(frozen=True)
class Episode:
    """One official episode: how the env is built (``gym.make`` kwargs beyond the robot's) and
    reset (``options``)."""

    env_id: str
    scene: str
    overlay: str | None  # file of ManiSkill2_real2sim/data/real_inpainting, or None
    build: tuple[tuple[str, Any], ...]  # extra env kwargs (urdf_version, station_name, ...)
    robot_xy: tuple[float, float]
    robot_yaw: float  # added to the base's 180 deg yaw
    obj: tuple[str, Any]  # ("init_xy", (x, y)) or ("episode_id", n)
    variant: str
    ray_tracing: bool = False  # the scripts' --enable-raytracing / shader_dir=rt

    @property
    def robot_quat(self) -> tuple[float, float, float, float]:
        return base_quat(self.robot_yaw)

    def reset_options(self) -> dict[str, Any]:
        key, value = self.obj
        return {
            "robot_init_options": {
                "init_xy": list(self.robot_xy),
                "init_rot_quat": list(self.robot_quat),
            },
            "obj_init_options": {key: list(value) if key == "init_xy" else int(value)},
        }

    def label(self) -> str:
        """What ``init_state_id`` says of the episode."""
        key, value = self.obj
        obj = f"obj_{value[0]:g}_{value[1]:g}" if key == "init_xy" else f"obj_episode_{value}"
        x, y = self.robot_xy
        return f"{self.variant}/rob_{x:g}_{y:g}_yaw_{self.robot_yaw:g}/{obj}"


@dataclass(frozen=True)
class SimplerTask:
    name: str  # SimplerEnv's task name
    robot: Robot
    max_steps: int
    instruction: str | None  # None: it depends on the episode (move near)
    setups: dict[str, list[Episode]] = field(hash=False, compare=False)


def base_quat(yaw: float) -> tuple[float, float, float, float]:
    """``(Pose(q=euler2quat(0, 0, yaw)) * Pose(q=[0, 0, 0, 1])).q`` of the scripts, (w, x, y,
    z): the robot base turned 180 deg (facing the scene) plus ``yaw``."""
    return (float(-np.sin(yaw / 2)), 0.0, 0.0, float(np.cos(yaw / 2)))


def grid(a: float, b: float, n: int) -> list[float]:
    """The scripts' ``a b n`` ranges: ``np.linspace`` with both ends."""
    return [float(v) for v in np.linspace(a, b, n)]


# -- actions ---------------------------------------------------------------------------------------

ROTATIONS = ("axis_angle", "rpy")


def to_sim_action(action: np.ndarray, family: str, rotation: str, binarize: bool) -> np.ndarray:
    """A policy's 7-d action -> the one SimplerEnv's env steps with.

    Both robots take ``[dx, dy, dz, rx, ry, rz, g]``: translation in metres in the robot base
    frame, rotation as an axis-angle vector (radians, base-frame axes); neither clips the arm.
    ``rotation="rpy"``: the action's [3:6] are roll, pitch, yaw (extrinsic x, y, z: transforms3d's
    ``sxyz``, what the Bridge and fractal datasets record and what SimplerEnv's Octo and RT-1-X
    wrappers convert with ``euler2axangle``), turned into that vector. ``axis_angle``: passed on
    (SimplerEnv's RT-1 on Google). The gripper: Google's is relative (the change of the finger
    target, clipped to [-1, 1] and scaled by 1.31 rad by the controller; > 0 closes), WidowX's is
    absolute (+1 open, -1 closed; SimplerEnv's Bridge wrappers binarize it: ``binarize``)."""
    a = np.asarray(action, dtype=np.float64).copy()
    if rotation == "rpy":
        from scipy.spatial.transform import Rotation

        a[3:6] = Rotation.from_euler("xyz", a[3:6]).as_rotvec()
    elif rotation != "axis_angle":
        raise ValueError(f"rotation={rotation!r}: one of {ROTATIONS}")
    if family == "google":
        a[6] = np.clip(a[6], -1.0, 1.0)
    elif binarize:
        a[6] = 1.0 if a[6] > 0 else -1.0
    return a
