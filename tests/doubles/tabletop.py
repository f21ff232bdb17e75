"""A tabletop env whose simulation diverges on purpose (its own module: importing it imports
the tabletop suite, which the fake-marker doubles do not need)."""

from __future__ import annotations

from typing import Any

from tests.doubles.instability import InjectsInstability
from workers.envs.suites.tabletop.env import TabletopEnv


class UnstableTabletopEnv(InjectsInstability, TabletopEnv):
    """TabletopEnv whose joint velocities are set to NaN inside MuJoCo's physics data just
    before control step ``inject_instability[1]`` of episode ``inject_instability[0]``, as a
    diverging simulation would leave them."""

    def __init__(self, inject_instability: tuple[int, int], **params: object) -> None:
        super().__init__(**params)  # type: ignore[arg-type]
        self._inject = tuple(inject_instability)  # type: ignore[assignment]

    def _physics_data(self) -> Any:
        return self._scene(self._ep.scene_key).sim.data._data
