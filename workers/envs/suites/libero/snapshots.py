"""LIBERO's lazy rendering: the simulator as robosuite's observables sampled it, rendered on read.

robosuite samples its observables at a substep inside the control step, not after the last one,
so rendering the final state would show another arm pose. With lazy rendering the simulator is
built without camera observables; ``MjData`` is copied (<1 ms) into a pooled ``MjData`` each time
robosuite samples ``SNAPSHOT_OBSERVABLE``, and reading a camera renders that copy with the call
robosuite's camera sensor makes (:func:`render_frame`). See ``LiberoEnv.__init__``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

# Lazy rendering snapshots the simulator when robosuite samples this observable. All observables
# sample at control_hz in lockstep, once per control step, at a substep that is not always the
# last (the 24th of 25 here, by the phase of their timers); the camera observables did the same.
SNAPSHOT_OBSERVABLE = "robot0_eef_pos"


class Frame:
    """The simulator as robosuite's observables sampled it: what a camera observable rendered.
    Its ``MjData`` goes back to the pool when the last observation holding it is dropped."""

    def __init__(self, pool: Snapshots, sim: Any, data: Any) -> None:
        self.pool, self.sim, self.data = pool, sim, data

    def __del__(self) -> None:
        self.pool.recycle(self.sim, self.data)


class Snapshots:
    """``MjData`` copies of one simulator taken at robosuite's sampling moments; ``latest`` is
    the last one. Copies go into recycled ``MjData``: each holds LIBERO's 1.3 GB (virtual)
    arena, too much to allocate per step; the pool stays at 2-3 while observations are dropped
    a step or two after they are made. No reference back to the env."""

    def __init__(self) -> None:
        self.latest: Frame | None = None
        self._sim: Any = None
        self._free: list[Any] = []

    def take(self, sim: Any) -> None:
        import mujoco

        if sim is not self._sim:  # a hard reset built a new simulator: start a new pool
            self._sim, self._free = sim, []
        model = sim.model._model
        data = self._free.pop() if self._free else mujoco.MjData(model)
        mujoco.mj_copyData(data, model, sim.data._data)
        self.latest = Frame(self, sim, data)

    def recycle(self, sim: Any, data: Any) -> None:
        if sim is self._sim and len(self._free) < 4:
            self._free.append(data)

    def clear(self) -> None:
        self.latest, self._sim, self._free = None, None, []


def install_snapshot(inner: Any, snapshots: Snapshots) -> None:
    """Copy ``MjData`` into ``snapshots`` whenever robosuite samples ``SNAPSHOT_OBSERVABLE``:
    the moments its camera observables rendered at. A filter doubles as an observer
    (robosuite's own words) and survives hard resets, which replace only sensors."""

    def snapshot(value: Any) -> Any:
        snapshots.take(inner.sim)
        return value

    inner.modify_observable(SNAPSHOT_OBSERVABLE, "filter", snapshot)


def render_frame(frame: Frame, camera: str, size: int) -> np.ndarray:
    """robosuite ``camera`` of ``frame`` as its camera sensor
    (``robot_env._create_camera_sensors``) renders it: the same ``sim.render`` call on the same
    context, with ``MjData`` swapped for the frame's copy, the only thing the render reads."""
    import types

    from robosuite import macros
    from robosuite.utils.mjcf_utils import IMAGE_CONVENTION_MAPPING

    ctx = frame.sim._render_context_offscreen
    ctx.gl_ctx.make_current()  # another env in this process may have made its own current
    live = ctx.data
    ctx.data = types.SimpleNamespace(_data=frame.data)
    try:
        img = frame.sim.render(camera_name=camera, width=size, height=size)
    finally:
        ctx.data = live
    return img[:: IMAGE_CONVENTION_MAPPING[macros.IMAGE_CONVENTION]]
