"""A LIBERO env whose simulation diverges on purpose (its own module: importing it imports the
LIBERO suite, which the other doubles do not need)."""

from __future__ import annotations

from typing import Any

from tests.doubles.instability import InjectsInstability
from workers.envs.suites.libero.env import LiberoEnv


class UnstableLiberoEnv(InjectsInstability, LiberoEnv):
    """LiberoEnv whose joint velocities are set to NaN inside MuJoCo's physics data just before
    control step ``inject_instability[1]`` of episode ``inject_instability[0]``."""

    def __init__(self, inject_instability: tuple[int, int], **params: object) -> None:
        super().__init__(**params)  # type: ignore[arg-type]
        self._inject = tuple(inject_instability)  # type: ignore[assignment]

    def _physics_data(self) -> Any:
        return self._sim.env.sim.data._data
