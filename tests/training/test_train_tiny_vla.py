"""The tiny VLA trainer: demonstrations in, a checkpoint the adapter loads out."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
@pytest.mark.sim
def test_train_script_produces_a_loadable_checkpoint(tmp_path) -> None:
    from training.tabletop_demos import record
    from training.train_tiny_vla import train
    from workers.backbones.base import Observation
    from workers.backbones.lerobot import LerobotBackbone

    record(tmp_path / "demos", ["pick_color"], episodes=1, image_size=32, first_episode=9)
    meta = train(
        [tmp_path / "demos"],
        tmp_path / "ckpt",
        steps=30,
        batch_size=16,
        log_every=10,
        state_noise=0.1,
        ignored_state_dims=(3, 4, 5),
    )
    assert meta["frames"] > 20 and meta["episodes"] == 1 and meta["steps"] == 30
    assert meta["ignored_state_dims"] == [3, 4, 5] and meta["state_noise"] == 0.1
    bb = LerobotBackbone(str(tmp_path / "ckpt"))
    assert bb.chunk_len == 8 and bb.image_shapes == {
        "observation.images.agentview": (3, 32, 32),
        "observation.images.wrist": (3, 32, 32),
    }
    # the ignored dims (end-effector orientation) cannot move the action; a position can
    g = torch.Generator().manual_seed(1)
    images = {c: torch.rand(1, 3, 32, 32, generator=g).expand(3, -1, -1, -1) for c in bb.cameras}
    state = torch.tensor([[0.0, 0.0, 0.9, 3.13, 0.0, 0.2, 0.02, -0.02]]).repeat(3, 1)
    state[1, 3:6] += torch.tensor([0.3, -0.2, 0.1])
    state[2, 0] += 0.1
    chunk = bb.predict_chunk(Observation(images, state, ["pick up the red cube"] * 3))
    assert torch.equal(chunk[0], chunk[1])
    assert (chunk[0] - chunk[2]).abs().max() > 1e-4

    # fine-tuning (--init) starts from the checkpoint's weights and keeps its normalization
    # stats (a policy's inputs must mean what they meant), not the new data's: shift the init
    # checkpoint's stats so that recomputing them from the data would show
    import shutil

    from safetensors.torch import load_file, save_file

    norm = "policy_preprocessor_step_3_normalizer_processor.safetensors"
    shutil.copytree(tmp_path / "ckpt", tmp_path / "init")
    shifted = {
        k: v + 1.0 if k.endswith(".mean") else v
        for k, v in load_file(tmp_path / "init" / norm).items()
    }
    save_file(shifted, tmp_path / "init" / norm)
    tuned = train(
        [tmp_path / "demos"],
        tmp_path / "tuned",
        steps=5,
        batch_size=16,
        log_every=5,
        ignored_state_dims=(3, 4, 5),
        init=tmp_path / "init",
        lr=1e-2,
    )
    assert tuned["init"] == str(tmp_path / "init") and tuned["steps"] == 5
    after = load_file(tmp_path / "tuned" / norm)
    assert after.keys() == shifted.keys()
    assert all(torch.equal(shifted[k], after[k]) for k in shifted)
    w0, w1 = (load_file(tmp_path / d / "model.safetensors") for d in ("ckpt", "tuned"))
    assert any(not torch.equal(w0[k], w1[k]) for k in w0)  # it did train
    # instructions with a word the checkpoint never saw are refused, naming the word
    cfg_path = tmp_path / "ckpt" / "config.json"
    cfg = json.loads(cfg_path.read_text())
    cfg["vocab"] = [w for w in cfg["vocab"] if w != "cube"]
    cfg_path.write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match=r"never saw: \['cube'\]"):
        train([tmp_path / "demos"], tmp_path / "bad", steps=1, init=tmp_path / "ckpt")

    # the architecture is chosen from scratch (a finer keypoint map, narrower layers) and saved
    # with the checkpoint; a fine-tune keeps its checkpoint's, so asking for one is refused
    arch = {"cnn_channels": (8, 16, 32), "cnn_strides": (2, 2, 1)}
    fine = train([tmp_path / "demos"], tmp_path / "fine", steps=3, batch_size=8, architecture=arch)
    assert fine["architecture"]["cnn_strides"] == [2, 2, 1] and fine["params"] < meta["params"]
    bb = LerobotBackbone(str(tmp_path / "fine"))
    enc = next(iter(bb.policy.cameras.values()))
    assert [c.stride for c in enc.convs] == [(2, 2), (2, 2), (1, 1)]
    assert [c.out_channels for c in enc.convs] == [8, 16, 32]
    feats = enc.convs[2](enc.convs[1](enc.convs[0](torch.zeros(1, 5, 32, 32))))
    assert feats.shape[-2:] == (8, 8)  # 32 px / 4, where strides 2 2 2 give 4 x 4
    with pytest.raises(ValueError, match="keeps its own architecture: leave out --cnn-strides"):
        train(
            [tmp_path / "demos"],
            tmp_path / "bad",
            steps=1,
            init=tmp_path / "fine",
            architecture={"cnn_strides": (2, 2, 2)},
        )
