"""Fake SIMPLER envs (tests only): registered under the official ids, recording every build,
reset and step in ``LOG`` (and, when ``$FAKE_SIMPLER_LOG`` is set, as JSON lines in that file, so
a test can read what an env server's fake did). No SAPIEN, no assets.

The SIMPLER adapter imports ``mani_skill2_real2sim.envs`` from the checkout it is pointed at;
tests build a throwaway checkout whose ``mani_skill2_real2sim/envs/__init__.py`` is this file
(tests/workers/envs/test_simpler.py), so nothing in the repository is named like the real one."""

from __future__ import annotations

import json
import os
from types import SimpleNamespace
from typing import Any

import gymnasium as gym
import numpy as np

LOG: list[dict[str, Any]] = []
IDS = (
    "OpenTopDrawerCustomInScene-v0",
    "CloseTopDrawerCustomInScene-v0",
    "PlaceIntoClosedTopDrawerCustomInScene-v0",
    "PutCarrotOnPlateInScene-v0",
    "MoveNearGoogleBakedTexInScene-v0",
    "GraspSingleOpenedCokeCanInScene-v0",
)
SUCCESS_STEPS = range(3, 6)  # success holds at steps 3-5 only: final-step vs any-step differ


def _log(entry: dict[str, Any]) -> None:
    LOG.append(entry)
    if path := os.environ.get("FAKE_SIMPLER_LOG"):
        with open(path, "a") as f:
            f.write(json.dumps(entry, default=lambda v: np.asarray(v).tolist()) + "\n")


class _Link:
    def __init__(self, name: str, p: list[float]) -> None:
        self.name = name
        self.pose = SimpleNamespace(p=np.array(p), q=np.array([0.0, 0.0, 0.0, 1.0]))


class _Robot:
    def __init__(self, uid: str) -> None:
        tcp = "link_gripper_tcp" if uid.startswith("google") else "ee_gripper_link"
        self.pose = SimpleNamespace(p=np.array([0.5, 0.0, 0.08]), q=np.array([0.0, 0.0, 0.0, 1.0]))
        self._links = [_Link("base_link", [0.5, 0.0, 0.08]), _Link(tcp, [0.3, 0.1, 0.9])]
        self._joints = [SimpleNamespace(name=n) for n in ("joint_a", "finger_r", "finger_l")]

    def get_links(self) -> list[_Link]:
        return self._links

    def get_active_joints(self) -> list[Any]:
        return self._joints

    def get_qpos(self) -> np.ndarray:
        return np.array([0.1, 0.2, 0.3])


class FakeSimplerSim(gym.Env):
    def __init__(self, env_id: str, **kwargs: Any) -> None:
        self.env_id, self.kwargs = env_id, kwargs
        self.camera = (
            "overhead_camera" if kwargs["robot"].startswith("google") else "3rd_view_camera"
        )
        self.agent = SimpleNamespace(robot=_Robot(kwargs["robot"]))
        self.elapsed = 0
        _log({"op": "make", "env_id": env_id, **kwargs})

    def _obs(self) -> dict[str, Any]:
        h = 512 if self.camera == "overhead_camera" else 480
        rgb = np.full((h, 640, 3), self.elapsed % 256, dtype=np.uint8)
        return {"image": {self.camera: {"rgb": rgb}}}

    def reset(self, seed: Any = None, options: dict[str, Any] | None = None) -> Any:
        self.elapsed = 0
        _log({"op": "reset", "seed": seed, "options": options})
        return self._obs(), {}

    def step(self, action: np.ndarray) -> Any:
        self.elapsed += 1
        _log({"op": "step", "action": np.asarray(action).tolist()})
        info = {"success": self.elapsed in SUCCESS_STEPS, "elapsed_steps": self.elapsed}
        return self._obs(), 0.0, info["success"], False, info

    def get_language_instruction(self) -> str:
        if self.env_id.startswith("PlaceInto"):  # the real env switches at step 100
            return "open top drawer" if self.elapsed < 100 else "place apple into top drawer"
        return "fake instruction"

    def close(self) -> None:
        _log({"op": "close"})


for _id in IDS:
    if _id not in gym.registry:
        gym.register(
            _id,
            entry_point=lambda _id=_id, **kw: FakeSimplerSim(_id, **kw),
            disable_env_checker=True,
        )
