"""Detect an unstable MuJoCo simulation instead of silently evaluating a reset one.

When positions, velocities or accelerations blow up (NaN, inf or huge values), MuJoCo prints
a warning, *resets the simulation to its initial state* and carries on: an episode would go on
from a teleported robot and be scored as if nothing happened. MuJoCo counts these events in
``MjData.warning``; :func:`raise_if_unstable` reads (and clears) those counters after a step
and raises :class:`SimulationUnstableError`, which ends the episode as an error row.
"""

from __future__ import annotations

from typing import Any


class SimulationUnstableError(RuntimeError):
    """The simulator diverged (NaN / inf / huge state); the episode cannot be scored."""


def _unstable_kinds() -> dict[int, str]:
    import mujoco

    w = mujoco.mjtWarning
    return {
        int(w.mjWARN_BADQPOS): "positions (qpos)",
        int(w.mjWARN_BADQVEL): "velocities (qvel)",
        int(w.mjWARN_BADQACC): "accelerations (qacc)",
    }


def mujoco_instability(data: Any) -> str | None:
    """A description of the instability MuJoCo recorded in ``data`` (an ``mujoco.MjData``)
    since the last call, or None; clears the counters it read."""
    found = []
    for kind, what in _unstable_kinds().items():
        w = data.warning[kind]
        if w.number > 0:
            found.append(f"NaN, inf or huge {what} at DOF {w.lastinfo} ({w.number}x)")
            w.number = 0
    return "; ".join(found) or None


def raise_if_unstable(data: Any, where: str) -> None:
    what = mujoco_instability(data)
    if what is not None:
        raise SimulationUnstableError(
            f"MuJoCo simulation unstable {where}: {what}; MuJoCo reset the state, so the "
            "episode is ended as an error instead of being scored"
        )
