"""The zoo's members: each lerobot architecture, its policy type and the flags that make it small
(``python -m training.zoo``), and the flags of a stage that trains on from an exported
checkpoint."""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from training.zoo_hub import SMOLVLM, XVLA_TOKENIZER, repo_id, xvla_florence_config


@dataclass(frozen=True)
class Member:
    """One zoo architecture: its lerobot policy type and the flags that make it small."""

    policy_type: str
    flags: tuple[str, ...]
    steps: int  # training steps of the shipped checkpoint (sized to ~60-90 min of 2 cores)
    batch_size: int
    language: bool  # whether the class conditions on the instruction
    save_freq: int = 1000
    vocab: bool = False  # the class takes its instruction vocabulary from the dataset's tasks
    # flags for one benchmark only (the tiny VLA masks the tabletop state's orientation dims)
    benchmark_flags: dict[str, tuple[str, ...]] = field(default_factory=dict)


MEMBERS: dict[str, Member] = {
    # ACT from scratch (no ImageNet download): a 2+1-layer transformer of width 256 over a
    # ResNet-18 per camera; chunks of 8, 4 executed (as the tiny VLA). No instruction input.
    "act": Member(
        "act",
        (
            "--policy.pretrained_backbone_weights=null",
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
            "--policy.dim_model=256",
            "--policy.dim_feedforward=1024",
            "--policy.n_encoder_layers=2",
            "--policy.n_decoder_layers=1",
            "--policy.optimizer_lr=1e-4",
            "--policy.optimizer_lr_backbone=1e-4",
        ),
        steps=6000,
        batch_size=32,
        language=False,
        save_freq=500,
    ),
    # Diffusion Policy from scratch: a small 1-D UNet (64-128-256) over a ResNet-18 with group
    # norm (required without pretrained weights); DDIM with 10 steps, so the three IDR passes can
    # share their noise exactly. No instruction input.
    "diffusion": Member(
        "diffusion",
        (
            "--policy.pretrained_backbone_weights=null",
            "--policy.use_group_norm=true",
            "--policy.horizon=16",
            "--policy.n_action_steps=8",
            "--policy.down_dims=[64,128,256]",
            "--policy.noise_scheduler_type=DDIM",
            "--policy.num_inference_steps=10",
            "--policy.n_obs_steps=1",
        ),
        steps=6000,
        batch_size=32,
        language=False,
        save_freq=500,
    ),
    # X-VLA, the paper's backbone: Florence-2 at small widths (training/zoo_hub.py) reads both
    # cameras and the instruction; the state enters with the action tokens of a 3-layer
    # transformer of width 128 (flow matching, 10 denoising steps). Tokenizer by hub id from the
    # local cache (installed by make setup), so the checkpoint loads from any folder.
    "xvla": Member(
        "xvla",
        (
            "--policy.florence_config=" + json.dumps(xvla_florence_config(), separators=(",", ":")),
            f"--policy.tokenizer_name={repo_id(XVLA_TOKENIZER)}",
            "--policy.tokenizer_max_length=16",
            "--policy.hidden_size=128",
            "--policy.depth=3",
            "--policy.num_heads=4",
            "--policy.num_domains=1",
            "--policy.len_soft_prompts=4",
            "--policy.dim_time=16",
            "--policy.action_mode=auto",
            "--policy.num_denoising_steps=10",
            "--policy.max_state_dim=8",
            "--policy.max_action_dim=7",
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
            # one learning rate for every part: lerobot's X-VLA preset gives the VLM a tenth of
            # it, meant for fine-tuning pretrained Florence-2 weights; here they start random
            "--use_policy_training_preset=false",
            "--optimizer.type=adamw",
            "--optimizer.lr=3e-4",
            "--optimizer.weight_decay=0.0",
            "--optimizer.grad_clip_norm=10",
            "--scheduler.type=cosine_decay_with_warmup",
            "--scheduler.peak_lr=3e-4",
            "--scheduler.decay_lr=1e-5",
            "--scheduler.num_warmup_steps=200",
            "--scheduler.num_decay_steps=6000",
        ),
        steps=6000,
        batch_size=32,
        language=True,
        save_freq=500,
    ),
    # SmolVLA: SmolVLM2 at small widths (training/zoo_hub.py: a 2-layer vision tower, a
    # 4-layer Llama of width 64) built from its config (no weights) and trained whole, with its
    # flow-matching action expert; instruction, both cameras at 96 px, state as a token.
    "smolvla": Member(
        "smolvla",
        (
            f"--policy.vlm_model_name={repo_id(SMOLVLM)}",
            "--policy.load_vlm_weights=false",
            # random VLM weights: train everything (the defaults freeze the VLM for fine-tuning)
            "--policy.train_expert_only=false",
            "--policy.freeze_vision_encoder=false",
            "--policy.resize_imgs_with_padding=[96,96]",
            "--policy.tokenizer_max_length=16",
            "--policy.num_vlm_layers=4",
            "--policy.num_expert_layers=4",
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
            "--policy.num_steps=10",
            "--policy.max_state_dim=8",
            "--policy.max_action_dim=7",
            # lerobot's preset (1e-4 after 1,000 warmup steps, decay over 30,000) is meant for
            # fine-tuning pretrained SmolVLM weights; these start random and small
            "--policy.optimizer_lr=3e-4",
            "--policy.scheduler_warmup_steps=200",
            "--policy.scheduler_decay_steps=6000",
        ),
        steps=6000,
        batch_size=32,
        language=True,
        save_freq=500,
    ),
    # the tiny VLA (our plugin's type), by lerobot's trainer on the zoo's dataset: the net, the
    # masked orientation dims and the chunking of the shipped one (docs/tiny-vla.md)
    "tiny_vla": Member(
        "tiny_vla",
        (
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
        ),
        steps=8000,
        batch_size=64,
        language=True,
        vocab=True,
        benchmark_flags={
            "tabletop": ("--policy.ignored_state_dims=[3,4,5]",),
            # runs where lerobot's MetaWorld env renders 480 px (the parity test)
            "metaworld": ("--policy.resize_images_to=96",),
        },
    ),
}


# the flags that size a learning-rate schedule to a run's steps: a continued stage decays over its
# own steps (its optimizer and schedule start afresh)
DECAY_FLAGS = ("--policy.scheduler_decay_steps=", "--scheduler.num_decay_steps=")


def stage_flags(flags: tuple[str, ...], steps: int) -> list[str]:
    """A member's flags with its schedule's decay sized to ``steps``."""
    return [next((f"{d}{steps}" for d in DECAY_FLAGS if f.startswith(d)), f) for f in flags]


def member_named(name: str) -> Member:
    if name not in MEMBERS:
        import difflib

        close = difflib.get_close_matches(name, MEMBERS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise SystemExit(f"unknown zoo member {name!r}{hint}; members: {sorted(MEMBERS)}")
    return MEMBERS[name]
