"""Expert demonstrations land in a LeRobotDataset that lerobot itself can read back."""

from __future__ import annotations

import pytest

pytestmark = [pytest.mark.sim, pytest.mark.slow]


def test_recorded_demos_load_as_lerobot_dataset(tmp_path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from workers.envs.tabletop_demos import record

    stats = record(tmp_path / "demos", ["pick_color"], episodes=1, image_size=32, first_episode=5)
    assert stats["pick_color"]["episodes"] == 1
    ds = LeRobotDataset("local/tabletop_demos", root=tmp_path / "demos")
    assert ds.num_episodes == 1 and ds.num_frames == stats["pick_color"]["frames"] and ds.fps == 20
    frame = ds[0]
    assert frame["observation.images.agentview"].shape == (3, 32, 32)
    assert frame["observation.images.wrist"].shape == (3, 32, 32)
    assert frame["observation.state"].shape == (8,) and frame["action"].shape == (7,)
    assert frame["task"].startswith("pick up the ") and frame["task"].endswith(" cube")
    last = ds[ds.num_frames - 1]
    assert last["action"][6] == 1.0  # the expert ends holding the lifted cube
