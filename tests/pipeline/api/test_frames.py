"""Held-out frames: each frame's progress through its episode and its gripper phase."""

from __future__ import annotations

import numpy as np

from pipeline.api.frames import episode_meta, gripper_phases


def test_gripper_phases_follow_the_demonstrations_command() -> None:
    closing = np.array([0, 0, 1, 1, 1, 0, 0, 1, 0], dtype=bool)
    assert gripper_phases(closing) == [
        "open", "open", "closed", "closed", "closed", "released", "released", "closed", "released"
    ]  # fmt: skip
    assert gripper_phases(np.zeros(4, dtype=bool)) == ["none"] * 4  # never grasps
    actions = np.zeros((11, 4), np.float32)
    actions[4:8, -1] = 1.0
    meta = episode_meta("t", 3, actions, gripper_dim=-1)
    assert meta["progress"].iloc[0] == 0 and meta["progress"].iloc[-1] == 1
    assert meta["fifth"].tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4, 4]  # progress t / 10
    assert meta["phase"].value_counts().to_dict() == {"open": 4, "closed": 4, "released": 3}
    assert set(episode_meta("t", 3, actions, gripper_dim=None)["phase"]) == {"none"}
