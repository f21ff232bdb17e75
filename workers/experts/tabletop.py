"""Scripted experts for the tabletop suite, from privileged simulator state.

The expert is a stateless feedback rule: from the cube positions, the grasp state and the
gripper opening it decides which phase it is in (travel above the cube, descend, close, carry,
lower, release), so a failed grasp or a dropped cube is simply tried again. It is usable as a
backbone (kind ``tabletop_expert``) so that ``idr-eval run conf/experts.yaml`` evaluates it,
and it records the demonstrations the tiny VLA is trained on (``tabletop_demos``).

It reads ``Observation.extras["privileged"]``, which only the tabletop env provides; it lives
env-side because it encodes the tasks' semantics, not a policy.
"""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import torch

from workers.envs.suites.tabletop.layout import BIN_CENTER, CUBE_HALF, TABLE_TOP_Z

HOVER_Z = TABLE_TOP_Z + 0.12  # eef height for travel (clears the bin walls with a cube held)
CARRY_Z = 0.09  # a held cube is lifted to this height above the table before it travels
GAIN = 25.0  # action per metre of position error (OSC: 1.0 = 5 cm per step)
XY_TOL = 0.012
# carry: the held cube is lowered once its xy is this close to the goal. The recordings behind
# checkpoints up to v7 used XY_TOL * 0.8; a wider tolerance makes the labels near the goal less
# sensitive to a centimetre of error (lower while correcting, rather than hover and correct)
PLACE_TOL = XY_TOL * 0.8
OPEN, CLOSE = -1.0, 1.0
BIN_SLOTS = np.array(
    [[-0.045, -0.045], [0.045, -0.045], [-0.045, 0.045], [0.045, 0.045], [0.0, 0.0]]
)


def _move(eef: np.ndarray, target: np.ndarray, gripper: float) -> np.ndarray:
    a = np.zeros(7)
    a[:3] = np.clip(GAIN * (target - eef), -1.0, 1.0)
    a[6] = gripper
    return a


def _goal(priv: dict[str, Any], cube: int) -> tuple[np.ndarray, float] | None:
    """Where the held cube goes: (xy, eef height at which to release); None = just lift it."""
    task = priv["task_id"]
    if task == "pick_color":
        return None
    if task == "stack_color":
        bottom = priv["cube_pos"][priv["targets"][1]]
        return bottom[:2], bottom[2] + 2 * CUBE_HALF + 0.008
    slot = BIN_SLOTS[priv["subtasks_done"]]
    return BIN_CENTER + slot, TABLE_TOP_Z + 0.008 + CUBE_HALF + 0.015


def expert_action(priv: dict[str, Any], place_tol: float = PLACE_TOL) -> np.ndarray:
    """One 7-d OSC action from the privileged state of the tabletop env.

    ``place_tol``: how close (xy, metres) the held cube must be to its goal before it is
    lowered and released; the lowering keeps correcting xy."""
    eef = priv["eef_pos"]
    width = float(priv["gripper_qpos"][0] - priv["gripper_qpos"][1])
    task = priv["task_id"]
    cube = (
        priv["targets"][0] if task != "organize" else priv["targets"][min(priv["subtasks_done"], 4)]
    )
    c = priv["cube_pos"][cube]
    if not priv["grasped"][cube]:
        if np.linalg.norm(eef[:2] - c[:2]) > XY_TOL:
            if eef[2] < c[2] + 0.05:  # low: rise before travelling, so as not to sweep cubes away
                return _move(eef, np.array([eef[0], eef[1], HOVER_Z]), OPEN)
            return _move(eef, np.array([c[0], c[1], HOVER_Z]), OPEN)
        if eef[2] > c[2] + 0.03 and width < 0.07:  # above the cube: open fully before descending
            return _move(eef, np.array([c[0], c[1], eef[2]]), OPEN)
        if eef[2] > c[2] + 0.004:
            return _move(eef, np.array([c[0], c[1], c[2] - 0.002]), OPEN)
        if width < 0.01:  # closed on nothing: back up and retry
            return _move(eef, np.array([c[0], c[1], c[2] + 0.06]), OPEN)
        return _move(eef, np.array([c[0], c[1], c[2]]), CLOSE)
    goal = _goal(priv, cube)
    if goal is None:  # pick: lift straight up
        return _move(eef, np.array([c[0], c[1], HOVER_Z]), CLOSE)
    xy, release_z = goal
    if np.linalg.norm(eef[:2] - xy) > place_tol:
        if c[2] < TABLE_TOP_Z + CARRY_Z and np.linalg.norm(eef[:2] - xy) > 0.03:
            return _move(eef, np.array([eef[0], eef[1], HOVER_Z]), CLOSE)  # lift before carrying
        return _move(
            eef, np.array([xy[0], xy[1], HOVER_Z if eef[2] > release_z + 0.03 else eef[2]]), CLOSE
        )
    if eef[2] > release_z + 0.004:
        return _move(eef, np.array([xy[0], xy[1], release_z]), CLOSE)
    return _move(eef, np.array([xy[0], xy[1], release_z]), OPEN)


class TabletopExpertBackbone:
    """The scripted expert behind the Backbone protocol (chunks of one action)."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset()
    can_batch = False
    cameras: tuple[str, ...] = ()  # privileged state only: nothing needs rendering

    def __init__(self, chunk_len: int = 1, place_tol: float = PLACE_TOL) -> None:
        if not 0.0 < place_tol < 2 * CUBE_HALF:
            raise ValueError(
                f"backbone.params.place_tol={place_tol}: must be in (0, {2 * CUBE_HALF}) metres"
            )
        self.place_tol = float(place_tol)
        if chunk_len != 1:
            raise ValueError(
                "backbone.params.chunk_len: the expert is closed-loop, use 1 (and replan_steps 1)"
            )
        self.name = "tabletop_expert"
        self.chunk_len = 1
        self.action_dim = 7

    def reset(self) -> None:
        pass

    def make_noise(self, batch_size: int, seed: int) -> None:
        return None

    def predict_chunk(self, obs: Any, noise: Any = None, intervention: Any = None) -> torch.Tensor:
        privs = obs.extras.get("privileged")
        if not privs or len(privs) != obs.batch_size:
            raise ValueError(
                "tabletop_expert needs privileged state: use it with env suite 'tabletop'"
            )
        actions = np.stack([expert_action(p, self.place_tol) for p in privs])
        return torch.from_numpy(actions).float()[:, None, :]
