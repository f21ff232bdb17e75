"""Small real lerobot policies built offline from their configs and saved as checkpoints."""

from __future__ import annotations

from pathlib import Path

import torch


def _features(image: int, state: int, action: int, cams: tuple[str, ...]):
    from lerobot.configs.types import FeatureType, PolicyFeature

    inputs = {
        f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, image, image))
        for c in cams
    }
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (state,))
    return inputs, {"action": PolicyFeature(FeatureType.ACTION, (action,))}


def _stats(image: int, state: int, action: int, cams: tuple[str, ...]) -> dict:
    g = torch.Generator().manual_seed(0)
    stats = {
        "observation.state": {
            "mean": torch.rand(state, generator=g),
            "std": 0.5 + torch.rand(state, generator=g),
            "min": -torch.ones(state),
            "max": torch.ones(state),
        },
        "action": {
            "mean": torch.rand(action, generator=g),
            "std": 0.5 + torch.rand(action, generator=g),
            "min": -torch.ones(action),
            "max": torch.ones(action),
        },
    }
    for c in cams:
        stats[f"observation.images.{c}"] = {
            "mean": torch.full((3, 1, 1), 0.4),
            "std": torch.full((3, 1, 1), 0.2),
            "min": torch.zeros(3, 1, 1),
            "max": torch.ones(3, 1, 1),
        }
    return stats


def save_checkpoint(policy, cfg, stats: dict, out: Path) -> Path:
    from lerobot.policies.factory import make_pre_post_processors

    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    policy.save_pretrained(out)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return out


def build_act(
    out: Path,
    image: int = 64,
    state: int = 8,
    action: int = 7,
    chunk: int = 10,
    cams: tuple[str, ...] = ("agentview",),
) -> Path:
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy

    inputs, outputs = _features(image, state, action, cams)
    cfg = ACTConfig(
        input_features=inputs,
        output_features=outputs,
        pretrained_backbone_weights=None,
        dim_model=64,
        n_heads=2,
        dim_feedforward=128,
        n_encoder_layers=1,
        n_decoder_layers=1,
        use_vae=False,
        chunk_size=chunk,
        n_action_steps=chunk,
        device="cpu",
    )
    torch.manual_seed(0)
    return save_checkpoint(ACTPolicy(cfg).eval(), cfg, _stats(image, state, action, cams), out)


def build_diffusion(out: Path, image: int = 64, state: int = 8, action: int = 7) -> Path:
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    inputs, outputs = _features(image, state, action, ("agentview",))
    cfg = DiffusionConfig(
        input_features=inputs,
        output_features=outputs,
        pretrained_backbone_weights=None,
        noise_scheduler_type="DDIM",
        num_inference_steps=3,
        down_dims=(32, 64),
        horizon=8,
        n_action_steps=4,
        n_obs_steps=1,
        crop_shape=None,
        device="cpu",
    )
    torch.manual_seed(0)
    return save_checkpoint(
        DiffusionPolicy(cfg).eval(), cfg, _stats(image, state, action, ("agentview",)), out
    )
