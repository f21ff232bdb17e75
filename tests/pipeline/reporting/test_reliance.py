"""Open-loop reliance on shared held-out frames: ``idr-eval reliance`` on two shipped MetaWorld
members over a small recorded dataset."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline import cli

ROOT = Path(__file__).resolve().parents[3]
ZOO = ROOT / "checkpoints" / "zoo" / "metaworld"


def _dataset(root: Path, episodes: int = 3, length: int = 15) -> None:
    """A small LeRobotDataset shaped as the MetaWorld demonstrations (96 px, 4-d state and
    action), each episode open, closed, then released."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    from training.metaworld_demos import FPS

    features = {
        "observation.image": {"dtype": "image", "shape": (96, 96, 3), "names": ["h", "w", "c"]},
        "observation.state": {"dtype": "float32", "shape": (4,), "names": None},
        "action": {"dtype": "float32", "shape": (4,), "names": None},
    }
    ds = LeRobotDataset.create(
        repo_id="local/heldout", fps=FPS, features=features, root=root, use_videos=False
    )
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        for t in range(length):
            grip = 1.0 if length // 3 <= t < 2 * length // 3 else -1.0
            ds.add_frame(
                {
                    "observation.image": rng.integers(0, 255, (96, 96, 3), dtype=np.uint8),
                    "observation.state": rng.normal(size=4).astype(np.float32),
                    "action": np.array([0.1, 0.0, -0.1, grip], np.float32),
                    "task": "Press a button",
                }
            )
        ds.save_episode()
    ds.finalize()


@pytest.mark.slow
def test_reliance_measures_every_member_on_the_same_frames(tmp_path: Path) -> None:
    frames = tmp_path / "heldout"
    _dataset(frames)
    out = tmp_path / "reliance"
    argv = ["reliance", str(frames), "--out", str(out), "--strategies", "tiny_vla"]
    argv += ["--member", f"tiny_vla={ZOO / 'tiny_vla'}", "--member", f"smolvla={ZOO / 'smolvla'}"]
    assert cli.main(argv) == 0
    result = json.loads((out / "reliance.json").read_text())
    assert result["frames"]["n"] == 45 and result["frames"]["episodes"] == 3
    table = pd.read_parquet(out / "reliance_frames.parquet")
    zero = table[table["strategy"] == "zero"]
    by_member = {m: g.reset_index(drop=True) for m, g in zero.groupby("member")}
    assert set(by_member) == {"tiny_vla", "smolvla"}
    keys = ["episode_index", "frame_index", "phase", "fifth"]
    assert by_member["tiny_vla"][keys].equals(by_member["smolvla"][keys])  # the same frames
    for name, rows in by_member.items():
        m = result["members"][name]
        want = rows["e_img"].sum() / (rows["e_img"].sum() + rows["e_prop"].sum() + 1e-6)
        assert m["r_img"] == pytest.approx(want)  # the ratio of mean effects
        assert m["ci95"][0] <= m["r_img"] <= m["ci95"][1]
        phases = {p: f["frames"] for p, f in m["by_phase"].items()}
        assert phases == {"open": 15, "closed": 15, "released": 15}
        assert sum(f["frames"] for f in m["by_fifth"]) == 45
    assert result["members"]["tiny_vla"]["r_img"] != result["members"]["smolvla"]["r_img"]
    strategies = result["strategies"]["by_strategy"]
    assert set(strategies) == {"zero", "mean", "gaussian"}
    assert strategies["zero"]["r_img"] == pytest.approx(result["members"]["tiny_vla"]["r_img"])
    assert strategies["mean"]["r_img"] != strategies["zero"]["r_img"]
    md = (out / "reliance.md").read_text()
    assert "fewer than the 2000 a finding needs" in md and "| tiny_vla |" in md
    assert (out / "figures" / "reliance_progress.png").is_file()


def test_bad_input_is_refused_before_the_frames_are_read(tmp_path: Path, capsys) -> None:
    missing = ["reliance", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]
    assert cli.main([*missing, "--member", f"a={ZOO / 'tiny_vla'}"]) == 2
    assert "is not a LeRobotDataset" in capsys.readouterr().err
    assert cli.main([*missing, "--member", "a=/no/such/ckpt"]) == 2
    assert "no such checkpoint folder" in capsys.readouterr().err
    assert cli.main([*missing, "--member", f"a={ZOO / 'tiny_vla'}", "--strategies", "b"]) == 2
    assert "--strategies 'b': not a member" in capsys.readouterr().err
