"""Fake environments for unit tests and the smoke preset. Not simulators: named as fakes.

``FakeMarkerEnv`` is a point agent on the plane [-1, 1]^2 that must reach a red marker whose
position is shown *only in the image* (the state is the agent's own position), so a policy
that ignores the image fails unless the marker happens to be near the centre. Task
``reach_chain`` shows three markers one after another: a 3-subtask chain that stops at the
first failure (when the step budget runs out), for Avg Len. ``SlowMarkerEnv`` is the same env
with a CPU-bound step, for benchmarks of how simulators and a policy overlap.
"""

from __future__ import annotations

import time
from typing import Annotated, ClassVar

import numpy as np

from workers.envs.base import EnvObservation, EpisodeStatus, TaskSpec
from workers.envs.episode_clock import EpisodeClock
from workers.param_doc import Doc

IMAGE_SIZE = 32
STEP_SCALE = 0.1  # position change per unit action per step
REACH_RADIUS = 0.08


def plane_to_pixel(xy: np.ndarray, size: int = IMAGE_SIZE) -> tuple[int, int]:
    """(x, y) in [-1, 1]^2 to (row, col); row 0 is y = +1."""
    col = int(np.clip(np.round((xy[0] + 1) / 2 * (size - 1)), 0, size - 1))
    row = int(np.clip(np.round((1 - xy[1]) / 2 * (size - 1)), 0, size - 1))
    return row, col


class FakeMarkerEnv:
    """Reach the red marker(s) seen in the image; deterministic init per (task, episode, seed)."""

    suite = "fake_marker"
    control_hz = 10.0
    action_dim = 2
    state_dim = 2
    cameras = ("agentview",)
    # the object-hidden render (mode pcd): the image without its marker
    renders_hidden_objects = True

    _TASKS = (
        TaskSpec("reach", "reach the marker", max_steps=40, subtasks_total=1),
        TaskSpec("reach_chain", "reach three markers in turn", max_steps=90, subtasks_total=3),
    )
    _INSTRUCTIONS: ClassVar[dict[str, str]] = {
        "reach": "move to the red marker",
        "reach_chain": "move to each red marker in turn",
    }

    def __init__(
        self, image_size: Annotated[int, Doc("px per side of the one camera")] = IMAGE_SIZE
    ) -> None:
        self.image_size = image_size
        self._clock = EpisodeClock(self.action_dim)
        self._pos = np.zeros(2)
        self._targets: list[np.ndarray] = []
        self._done_count = 0

    @classmethod
    def suite_tasks(cls, **_: object) -> list[TaskSpec]:
        return list(cls._TASKS)

    def tasks(self) -> list[TaskSpec]:
        return list(self._TASKS)

    def _spec(self, task_id: str) -> TaskSpec:
        for t in self._TASKS:
            if t.task_id == task_id:
                return t
        raise ValueError(
            f"task_id={task_id!r} unknown; allowed: {[t.task_id for t in self._TASKS]}"
        )

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        spec = self._spec(task_id)
        task_index = self._TASKS.index(spec)
        rng = np.random.default_rng([seed, episode_index, task_index])
        self._clock.start(spec)
        self._pos = rng.uniform(-0.9, 0.9, size=2)
        self._targets = [rng.uniform(-0.9, 0.9, size=2) for _ in range(spec.subtasks_total)]
        self._done_count = 0
        return self._observe()

    def object_hidden_images(self) -> dict[str, np.ndarray]:
        """The current image with the task's object, its marker, left out."""
        return {"agentview": self._image(marker=False)}

    def _observe(self) -> EnvObservation:
        return EnvObservation(
            images={"agentview": self._image()},
            state=self._pos.astype(np.float32),
            status=self._status(),
        )

    def _image(self, marker: bool = True) -> np.ndarray:
        img = np.zeros((self.image_size, self.image_size, 3), dtype=np.uint8)
        if marker and self._done_count < len(self._targets):
            r, c = plane_to_pixel(self._targets[self._done_count], self.image_size)
            img[max(r - 1, 0) : r + 2, max(c - 1, 0) : c + 2, 0] = 255
        r, c = plane_to_pixel(self._pos, self.image_size)
        img[r, c, 1] = 255
        return img

    def _status(self) -> EpisodeStatus:
        task = self._clock.task
        assert task is not None
        success = self._done_count == task.subtasks_total
        return self._clock.status(
            self._INSTRUCTIONS[task.task_id],
            success,
            ended=success,
            subtasks_done=self._done_count,
        )

    def step(self, action: np.ndarray) -> EnvObservation:
        self._move(self._clock.take(action))
        return self._observe()

    def _move(self, action: np.ndarray) -> None:
        """The point's dynamics and the marker check of one step."""
        self._pos = np.clip(self._pos + STEP_SCALE * np.clip(action, -1, 1), -1, 1)
        target = self._targets[self._done_count]
        if np.linalg.norm(self._pos - target) < REACH_RADIUS:
            self._done_count += 1

    def close(self) -> None:
        self._clock = EpisodeClock(self.action_dim)


class SlowMarkerEnv(FakeMarkerEnv):
    """FakeMarkerEnv whose step keeps a core busy for ``step_ms`` (a simulator's physics and
    rendering, CPU-bound and holding the GIL as MuJoCo's Python loop would): for measuring how
    simulators and a policy overlap, without a simulator's noise."""

    def __init__(
        self,
        image_size: Annotated[int, Doc("px per side of the one camera")] = IMAGE_SIZE,
        step_ms: Annotated[float, Doc("ms of busy CPU per step, before the step itself")] = 15.0,
    ) -> None:
        super().__init__(image_size=image_size)
        self.step_s = step_ms / 1e3

    def step(self, action: np.ndarray) -> EnvObservation:
        end = time.perf_counter() + self.step_s
        while time.perf_counter() < end:
            pass
        return super().step(action)
