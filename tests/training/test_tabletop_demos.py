"""Expert demonstrations land in a LeRobotDataset that lerobot itself can read back."""

from __future__ import annotations

import pytest

pytestmark = [pytest.mark.sim, pytest.mark.slow]


def test_recorded_demos_load_as_lerobot_dataset(tmp_path) -> None:
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from training.tabletop_demos import record

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


def test_dart_noise_and_dagger_driver_keep_expert_labels(tmp_path) -> None:
    """DART: noisy execution, clean labels, only successes kept. DAgger: a (here untrained)
    policy drives, every visited state is kept with the expert's label, success or not."""
    import numpy as np
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from training.tabletop_demos import record
    from training.train_tiny_vla import train

    record(tmp_path / "clean", ["pick_color"], episodes=1, image_size=32, first_episode=7)
    noisy = record(
        tmp_path / "dart", ["pick_color"], episodes=1, image_size=32, first_episode=7, noise=0.5
    )
    # same init state, noisy execution: another trajectory, still a success
    assert noisy["pick_color"]["episodes"] == 1
    a_clean = LeRobotDataset("local/tabletop_demos", root=tmp_path / "clean")
    a_noisy = LeRobotDataset("local/tabletop_demos", root=tmp_path / "dart")
    assert not np.allclose(a_clean[5]["observation.state"], a_noisy[5]["observation.state"])

    train([tmp_path / "clean"], tmp_path / "ckpt", steps=5, batch_size=8, log_every=5)
    stats = record(
        tmp_path / "dagger",
        ["pick_color"],
        episodes=1,
        image_size=32,
        first_episode=11,
        policy=tmp_path / "ckpt",
    )
    assert stats["pick_color"]["tried"] == 1  # kept although a 5-step policy cannot succeed
    ds = LeRobotDataset("local/tabletop_demos", root=tmp_path / "dagger")
    labels = np.stack([ds[i]["action"].numpy() for i in range(ds.num_frames)])
    assert ds.num_frames == stats["pick_color"]["frames"] > 20
    assert np.abs(labels[:, :3]).max() <= 1.0 and set(np.unique(labels[:, 6])) <= {-1.0, 1.0}


def test_sigint_stops_after_the_episode_and_leaves_a_readable_dataset(tmp_path) -> None:
    import json
    import re
    import signal
    import subprocess
    import sys
    import time

    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    root = tmp_path / "demos"
    cmd = [sys.executable, "-m", "training.tabletop_demos", "--root", str(root)]
    proc = subprocess.Popen(
        [*cmd, "--episodes", "50", "--tasks", "pick_color", "--image-size", "32"],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    info = root / "meta" / "info.json"
    deadline = time.monotonic() + 240
    while not (info.is_file() and json.loads(info.read_text())["total_episodes"] >= 1):
        assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read()
        time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    # and again, as an impatient user or a scheduler repeating SIGTERM would, until it exits:
    # a signal during finalize must not leave an unreadable dataset
    while proc.poll() is None and time.monotonic() < deadline:
        proc.send_signal(signal.SIGTERM)
        time.sleep(0.05)
    out, _ = proc.communicate(timeout=120)
    # a SIGTERM that lands after the dataset is finalized may end the process (handlers are
    # restored then): the data is what must survive. The first signal recorded is the SIGINT,
    # or, when it landed while a library in the dataset writer held SIGINT's handler (seen
    # once in five clean-clone runs), the first SIGTERM of the storm: either way it stopped
    # after the episode in progress
    assert proc.returncode in (0, -signal.SIGTERM), out
    assert re.search(rf"stopped by signal ({signal.SIGINT:d}|{signal.SIGTERM:d}): ", out), out
    ds = LeRobotDataset("local/tabletop_demos", root=root)
    assert 1 <= ds.num_episodes < 50
    assert ds[ds.num_frames - 1]["observation.state"].shape == (8,)
