"""What a SIMPLER observation's state and privileged state are, read off ManiSkill2_real2sim's
env (``env.unwrapped``): poses in the robot base frame (SAPIEN quaternions are (w, x, y, z))."""

from __future__ import annotations

from typing import Any

import numpy as np


def _base_inv(u: Any) -> Any:
    """The world-to-robot-base rotation."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.roll(u.agent.robot.pose.q, -1)).inv()


def _in_base(u: Any, pose: Any) -> np.ndarray:
    """A SAPIEN pose's position in the robot base frame."""
    base = u.agent.robot.pose
    return _base_inv(u).apply(np.asarray(pose.p) - np.asarray(base.p))


def robot_state(u: Any, tcp_link: str) -> np.ndarray:
    """(8,) float32: the TCP pose in the robot base frame (position, axis-angle) and the two
    finger joints."""
    from scipy.spatial.transform import Rotation

    agent = u.agent
    tcp = next(x for x in agent.robot.get_links() if x.name == tcp_link).pose
    pos = _in_base(u, tcp)
    rot = (_base_inv(u) * Rotation.from_quat(np.roll(tcp.q, -1))).as_rotvec()
    joints = agent.robot.get_active_joints()
    qpos = agent.robot.get_qpos()
    fingers = [qpos[i] for i, j in enumerate(joints) if "finger" in j.name][:2]
    return np.concatenate([pos, rot, np.resize(fingers or [0.0], 2)]).astype(np.float32)


def privileged_state(u: Any, state: np.ndarray) -> dict[str, Any]:
    """Simulator state for scripted controllers in tests (never for learned policies): the TCP
    (of the observation's ``state``) and, in the drawer tasks, the target drawer's link origin,
    in the robot base frame, and the drawer's opening (m)."""
    out: dict[str, Any] = {"tcp_pos": state[:3].astype(np.float64)}
    if getattr(u, "drawer_obj", None) is not None:
        out["drawer_pos"] = _in_base(u, u.drawer_obj.pose)
        out["drawer_qpos"] = float(u.art_obj.get_qpos()[u.joint_idx])
    return out
