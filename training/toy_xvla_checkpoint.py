"""A toy X-VLA checkpoint (``training.toy_checkpoints``' kind: real lerobot classes, random
weights, built offline).

lerobot's XVLAConfig() has no Florence-2 part (it normally comes from the hub with a
checkpoint: "vision_config is required"). Here it is spelled out at tiny widths (DaViT in two
stages, three above 64 px; a one-layer BART), with a local word-level tokenizer instead of facebook/bart-large
(``training.toy_checkpoints.build_local_tokenizer``): the same classes and code paths, random
weights."""

from __future__ import annotations

from pathlib import Path

import torch

from training.toy_checkpoints import _features, _stats, save_checkpoint

XVLA_VOCAB = 320  # the tokenizer's ids fit below it; the image token takes the last id


def xvla_florence_config(vocab: int = XVLA_VOCAB, image: int = 64) -> dict:
    """``image``: the camera's size in px; above 64 px a third DaViT stage (stride 2) keeps
    the image tokens within the one-layer BART's 128 positions (96 px: 6 x 6 tokens)."""
    stages = 3 if image > 64 else 2
    return {
        "vision_config": {
            "model_type": "florence_vision",
            "depths": [1] * stages,
            "patch_size": [7, 3, 3][:stages],
            "patch_stride": [4, 2, 2][:stages],
            "patch_padding": [3, 1, 1][:stages],
            "patch_prenorm": [False, True, True][:stages],
            "embed_dim": [16, 32, 32][:stages],
            "num_heads": [1, 2, 2][:stages],
            "num_groups": [1, 2, 2][:stages],
            "window_size": 4,
            "drop_path_rate": 0.0,
            "projection_dim": 32,
            "max_position_embeddings": 16,
            "max_temporal_embeddings": 4,
        },
        "text_config": {
            "model_type": "bart",
            "vocab_size": vocab,
            "d_model": 32,
            "encoder_layers": 1,
            "decoder_layers": 1,
            "encoder_attention_heads": 2,
            "decoder_attention_heads": 2,
            "encoder_ffn_dim": 64,
            "decoder_ffn_dim": 64,
            "max_position_embeddings": 128,
        },
        "image_token_id": vocab - 1,
        "pad_token_id": 0,
        "bos_token_id": 2,
        "eos_token_id": 1,
    }


def build_xvla(
    out: Path,
    tokenizer_dir: Path,
    image: int = 64,
    state: int = 8,
    action: int = 7,
    chunk: int = 4,
    cams: tuple[str, ...] = ("agentview",),
) -> Path:
    """A random-weight X-VLA checkpoint built offline (tiny Florence-2, action mode ``auto``),
    whose saved preprocessor names the local tokenizer folder."""
    from lerobot.policies.xvla.configuration_xvla import XVLAConfig
    from lerobot.policies.xvla.modeling_xvla import XVLAPolicy

    inputs, outputs = _features(image, state, action, cams)
    cfg = XVLAConfig(
        input_features=inputs,
        output_features=outputs,
        florence_config=xvla_florence_config(image=image),
        tokenizer_name=str(tokenizer_dir),
        tokenizer_max_length=16,
        hidden_size=32,
        depth=1,
        num_heads=2,
        num_domains=2,
        len_soft_prompts=4,
        dim_time=8,
        max_len_seq=128,
        action_mode="auto",
        num_denoising_steps=2,
        max_state_dim=state,
        max_action_dim=action,
        chunk_size=chunk,
        n_action_steps=chunk,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = XVLAPolicy(cfg).eval()
    return save_checkpoint(policy, cfg, _stats(image, state, action, cams), out)
