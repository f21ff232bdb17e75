"""A FAKE lerobot robot plugin for tests: a 6-joint arm with one camera and no hardware.

The test writes this file into a throwaway site folder as the package
``lerobot_robot_fake_camera_arm`` with a ``.dist-info`` beside it, so lerobot's own plugin
discovery (``register_third_party_plugins``: distributions named ``lerobot_robot_*``) finds it
in a ``lerobot-rollout`` subprocess, as it would a real robot's plugin (lerobot_robot_arx5).
Observations are deterministic functions of the last action; every action sent is appended
to ``action_log`` (JSON lines), so the test can check the action stream is complete.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from lerobot.robots.config import RobotConfig
from lerobot.robots.robot import Robot

JOINTS = tuple(f"joint{i}" for i in range(6))


@RobotConfig.register_subclass("fake_camera_arm")
@dataclass
class FakeCameraArmConfig(RobotConfig):
    action_log: str = "fake_arm_actions.jsonl"
    image_size: int = 64


class FakeCameraArm(Robot):
    """FAKE: joints follow the commanded positions; the camera shows a colour that depends on
    the first joint, so the policy's image input changes with the motion."""

    config_class = FakeCameraArmConfig
    name = "fake_camera_arm"

    def __init__(self, config: FakeCameraArmConfig) -> None:
        super().__init__(config)
        self.config = config
        self._connected = False
        self._q = np.zeros(len(JOINTS), dtype=np.float32)

    @cached_property
    def observation_features(self) -> dict:
        s = self.config.image_size
        return {**{f"{j}.pos": float for j in JOINTS}, "front": (s, s, 3)}

    @cached_property
    def action_features(self) -> dict:
        return {f"{j}.pos": float for j in JOINTS}

    @property
    def is_connected(self) -> bool:
        return self._connected

    def connect(self, calibrate: bool = True) -> None:
        self._connected = True

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        return None

    def configure(self) -> None:
        return None

    def get_observation(self) -> dict:
        s = self.config.image_size
        level = int(np.clip(128 + 100 * np.tanh(self._q[0]), 0, 255))
        image = np.full((s, s, 3), level, dtype=np.uint8)
        image[: s // 2, :, 1] = 255 - level
        return {
            **{f"{j}.pos": float(q) for j, q in zip(JOINTS, self._q, strict=True)},
            "front": image,
        }

    def send_action(self, action: dict) -> dict:
        self._q = np.array([float(action[f"{j}.pos"]) for j in JOINTS], dtype=np.float32)
        with Path(self.config.action_log).open("a") as f:
            f.write(
                json.dumps({"t": time.time(), **{k: float(v) for k, v in action.items()}}) + "\n"
            )
        return action

    def disconnect(self) -> None:
        self._connected = False
