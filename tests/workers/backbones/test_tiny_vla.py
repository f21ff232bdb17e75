"""The tiny VLA: a lerobot policy type of our own, trained by a script, loaded by the adapter."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from lerobot_policy_idr.tiny_vla.modeling_tiny_vla import tokenize

ROOT = Path(__file__).resolve().parents[3]
SHIPPED = ROOT / "checkpoints" / "tiny_vla"


def test_tokenize_keeps_order_and_marks_unknown_words() -> None:
    ids = tokenize(
        ["Put the red, blue cubes", "the zebra"], ["blue", "cubes", "put", "red", "the"], 6
    )
    assert ids.tolist() == [[4, 6, 5, 2, 3, 0], [6, 1, 0, 0, 0, 0]]


def test_shipped_checkpoint_is_small_safetensors_and_loads_through_the_adapter() -> None:
    from workers.backbones.base import Observation
    from workers.backbones.lerobot import LerobotBackbone

    files = {p.name for p in SHIPPED.iterdir()}
    assert {
        "config.json",
        "model.safetensors",
        "policy_preprocessor.json",
        "policy_postprocessor.json",
    } <= files
    assert sum(p.stat().st_size for p in SHIPPED.rglob("*") if p.is_file()) < 20 * 2**20
    assert json.loads((SHIPPED / "config.json").read_text())["type"] == "tiny_vla"
    meta = json.loads((SHIPPED / "train_meta.json").read_text())
    assert meta["command"].startswith("python -m training.train_tiny_vla")
    bb = LerobotBackbone(str(SHIPPED))
    assert bb.cameras == ("agentview", "wrist") and bb.state_dim == 8 and bb.action_dim == 7
    assert bb.crn_mode == "deterministic" and bb.can_batch  # one 3B forward for IDR
    g = torch.Generator().manual_seed(0)
    images = {c: torch.rand(1, 3, 96, 96, generator=g).expand(2, -1, -1, -1) for c in bb.cameras}
    obs = Observation(
        images, torch.zeros(2, 8) + 0.5, ["pick up the red cube", "pick up the blue cube"]
    )
    chunk = bb.predict_chunk(obs)
    assert chunk.shape == (2, 8, 7) and torch.isfinite(chunk).all()
    # the instruction matters: same image and state, another color, another action
    assert (chunk[0] - chunk[1]).abs().max() > 1e-3


def test_ignored_state_dims_outside_the_state_are_refused() -> None:
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot_policy_idr.tiny_vla.configuration_tiny_vla import TinyVLAConfig

    cfg = TinyVLAConfig(
        input_features={
            "observation.images.agentview": PolicyFeature(FeatureType.VISUAL, (3, 32, 32)),
            "observation.state": PolicyFeature(FeatureType.STATE, (8,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
        ignored_state_dims=[3, 8],
    )
    with pytest.raises(ValueError, match=r"ignored_state_dims \[8\] outside the state's 8 dims"):
        cfg.validate_features()
    cfg.ignored_state_dims = [3]
    cfg.cnn_strides = (2, 2)
    with pytest.raises(ValueError, match=r"cnn_strides \[2, 2\] needs one stride per layer"):
        cfg.validate_features()


def test_resize_images_to_feeds_the_net_the_size_it_was_trained_on() -> None:
    """The zoo's MetaWorld tiny VLA (trained at 96 px, ``resize_images_to: 96``) given a 480 px
    frame acts as on that frame resized to 96 px; the same net without the resize acts otherwise
    (its CNN is fully convolutional, so it would run on 480 px, on features it never saw)."""
    import torch.nn.functional as F
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class

    path = ROOT / "checkpoints" / "zoo" / "metaworld" / "tiny_vla"
    cfg = PreTrainedConfig.from_pretrained(path)
    assert cfg.resize_images_to == 96
    policy = get_policy_class("tiny_vla").from_pretrained(path, config=cfg).eval()
    big = torch.rand(1, 3, 480, 480, generator=torch.Generator().manual_seed(0))
    small = F.interpolate(big, size=(96, 96), mode="bilinear", antialias=True, align_corners=False)
    batch = {"observation.state": torch.zeros(1, 4), "task": ["Press a button"]}
    resized = policy.predict_action_chunk({**batch, "observation.image": big})
    assert torch.equal(resized, policy.predict_action_chunk({**batch, "observation.image": small}))
    policy.config.resize_images_to = None
    as_given = policy.predict_action_chunk({**batch, "observation.image": big})
    assert (as_given - resized).abs().max() > 1e-3
    cfg.resize_images_to = 4
    with pytest.raises(ValueError, match=r"resize_images_to=4: give a size of at least 8 px"):
        cfg.validate_features()
