"""A simulation that diverges on purpose: joint velocities set to NaN inside MuJoCo's physics
data just before control step ``inject_instability[1]`` of episode ``inject_instability[0]``,
as a diverging simulation would leave them (mixed into the suites' envs by their doubles)."""

from __future__ import annotations

from typing import Any

import numpy as np


class InjectsInstability:
    """Mixin over an env with an ``EpisodeClock`` (``_clock``), ``reset`` and ``step``; the env
    says where its MuJoCo data is (``_physics_data``)."""

    _inject: tuple[int, int] = (-1, -1)
    _episode: int = -1

    def _physics_data(self) -> Any:
        raise NotImplementedError

    def reset(self, task_id: str, episode_index: int, seed: int) -> Any:
        self._episode = episode_index
        return super().reset(task_id, episode_index, seed)  # type: ignore[misc]

    def step(self, action: np.ndarray) -> Any:
        clock = self._clock  # type: ignore[attr-defined]
        if self._inject == (self._episode, clock.steps) and not clock.done:
            self._physics_data().qvel[:] = np.nan
        return super().step(action)  # type: ignore[misc]
