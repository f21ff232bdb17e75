"""A LIBERO env whose simulation diverges on purpose (its own module: importing it imports the
LIBERO suite, which the other doubles do not need)."""

from __future__ import annotations

import numpy as np

from workers.envs.base import EnvObservation
from workers.envs.libero import LiberoEnv


class UnstableLiberoEnv(LiberoEnv):
    """LiberoEnv whose joint velocities are set to NaN inside MuJoCo's physics data just before
    control step ``inject_instability[1]`` of episode ``inject_instability[0]``, as a diverging
    simulation would leave them."""

    def __init__(self, inject_instability: tuple[int, int], **params: object) -> None:
        super().__init__(**params)  # type: ignore[arg-type]
        self._inject = tuple(inject_instability)
        self._episode = -1

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        self._episode = episode_index
        return super().reset(task_id, episode_index, seed)

    def step(self, action: np.ndarray) -> EnvObservation:
        if self._inject == (self._episode, self.steps) and not self.done:
            self._sim.env.sim.data._data.qvel[:] = np.nan
        return super().step(action)
