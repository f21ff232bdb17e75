"""A toy local Qwen3-VL folder and lerobot's VLA-JEPA policy on it, with no hub: random weights
at toy widths, the toy byte-level BPE tokenizer of ``vlm_fixtures`` with Qwen's special tokens,
and the processor files ``AutoProcessor`` reads (image + video processor configs, chat template).

- Qwen3-VL (transformers' own ``Qwen3VLForConditionalGeneration``, no remote code): VLA-JEPA's
  ``qwen_model_name`` instead of ``Qwen/Qwen3-VL-2B-Instruct``;
- VLA-JEPA without its world model (``enable_world_model=False``: no V-JEPA 2 encoder from the
  hub; inference never uses it), a two-layer DiT action head at toy widths.
"""

from __future__ import annotations

import math
from pathlib import Path

import torch

from tests.workers.backbones.vlm_fixtures import (
    CHAT_TEMPLATE,
    fresh_dir,
    qwen_text_config,
    qwen_vision_token_ids,
    save_random,
    toy_tokenizer_and_ids,
)
from training.toy_checkpoints import _features, _stats, save_checkpoint

# ----------------------------------------------------------------------------------------------
# Toy sizes
# ----------------------------------------------------------------------------------------------
QWEN3VL_PATCH = 16  # vision patch size (same as real Qwen3-VL)
QWEN3VL_MERGE = 2  # spatial merge (same as real)
QWEN3VL_TEMPORAL_PATCH = 2  # same as real
QWEN3VL_MIN_PIXELS = 32 * 32  # a 64x64 camera frame stays 64x64 ...
QWEN3VL_MAX_PIXELS = 64 * 64  # ... -> grid (1, 4, 4) = 16 patches = 4 image tokens per image
QWEN3VL_TEXT_HIDDEN = 64
QWEN3VL_TEXT_HEADS = 4
QWEN3VL_HEAD_DIM = 16  # rotary half-dim 8 = sum(mrope_section), interleaved T/H/W as the real one
QWEN3VL_MROPE_SECTION = [4, 2, 2]
QWEN3VL_VISION_DEPTH = 2
QWEN3VL_DEEPSTACK = [0, 1]  # vision layers whose features are added to text layers 0 and 1
# Head-room in the vocabulary for the tokens VLA-JEPA adds at load time (chunk_size * 4
# "<|action_i|>" + "<|embodied_action|>"), so it never resizes the embeddings (as with the real
# Qwen3-VL, whose 151936-row embedding exceeds its tokenizer): chunks up to 31 fit.
QWEN3VL_VOCAB_HEADROOM = 128
# Weight init std (real: 0.02). At 0.02 and these widths attention is near-uniform over VLA-JEPA's
# ~110-token prompt and its 4 image tokens barely move the embodied-action states (zeroing the
# image changes the raw action chunk by ~3e-4, while lerobot runs Qwen under bf16 autocast even
# on CPU); at 0.1 by ~3e-2. The full model initializes every module, vision included, with
# text_config.initializer_range (Qwen3VLConfig itself has none); the vision value is for show.
QWEN3VL_INIT_STD = 0.1
QWEN_IMAGE_MEAN = [0.5, 0.5, 0.5]  # Qwen3-VL's (not CLIP's, as Qwen2.5-VL)
QWEN_IMAGE_STD = [0.5, 0.5, 0.5]

# Qwen3-VL's chat template renders like Qwen2.5-VL's but adds no default system message.
_DEFAULT_SYSTEM = (
    "{% if loop.first and message['role'] != 'system' %}<|im_start|>system\n"
    "You are a helpful assistant.<|im_end|>\n{% endif %}"
)
assert _DEFAULT_SYSTEM in CHAT_TEMPLATE
QWEN3VL_CHAT_TEMPLATE = CHAT_TEMPLATE.replace(_DEFAULT_SYSTEM, "")


def build_qwen3vl_folder(out: str | Path) -> Path:
    """Write a random-weight toy Qwen3-VL checkpoint + every processor file into `out`."""
    from transformers import (
        Qwen2VLImageProcessor,
        Qwen3VLConfig,
        Qwen3VLForConditionalGeneration,
        Qwen3VLVideoProcessor,
    )

    out = fresh_dir(out)

    # 1) Tokenizer (Qwen2Tokenizer, as Qwen3-VL's).
    tokenizer, ids = toy_tokenizer_and_ids()

    # 2) Image / video processors: small pixel budget, real patch geometry and normalization.
    geometry = dict(
        patch_size=QWEN3VL_PATCH,
        temporal_patch_size=QWEN3VL_TEMPORAL_PATCH,
        merge_size=QWEN3VL_MERGE,
    )
    norm = dict(image_mean=QWEN_IMAGE_MEAN, image_std=QWEN_IMAGE_STD)
    size = {"shortest_edge": QWEN3VL_MIN_PIXELS, "longest_edge": QWEN3VL_MAX_PIXELS}
    Qwen2VLImageProcessor(size=size, **geometry, **norm).save_pretrained(out)
    Qwen3VLVideoProcessor(size=size, **geometry, **norm).save_pretrained(out)
    # Hub-style layout (like Qwen/Qwen3-VL-2B-Instruct): one file per component.
    tokenizer.save_pretrained(out)
    (out / "chat_template.jinja").write_text(QWEN3VL_CHAT_TEMPLATE)

    # 3) Model config.
    vocab_size = int(math.ceil((len(tokenizer) + QWEN3VL_VOCAB_HEADROOM) / 64) * 64)
    config = Qwen3VLConfig(
        text_config=qwen_text_config(
            ids,
            vocab_size,
            QWEN3VL_TEXT_HIDDEN,
            QWEN3VL_TEXT_HEADS,
            head_dim=QWEN3VL_HEAD_DIM,
            rope_parameters={
                "rope_type": "default",
                "rope_theta": 10000.0,
                "mrope_section": QWEN3VL_MROPE_SECTION,
                "mrope_interleaved": True,
            },
            initializer_range=QWEN3VL_INIT_STD,
        ),
        vision_config=dict(
            depth=QWEN3VL_VISION_DEPTH,
            hidden_size=32,
            intermediate_size=64,
            num_heads=2,
            in_channels=3,
            patch_size=QWEN3VL_PATCH,
            spatial_merge_size=QWEN3VL_MERGE,
            temporal_patch_size=QWEN3VL_TEMPORAL_PATCH,
            out_hidden_size=QWEN3VL_TEXT_HIDDEN,
            num_position_embeddings=64,  # an 8 x 8 learned grid, bilinearly interpolated
            deepstack_visual_indexes=QWEN3VL_DEEPSTACK,
            initializer_range=QWEN3VL_INIT_STD,
        ),
        **qwen_vision_token_ids(ids),
        tie_word_embeddings=False,
    )
    return save_random(Qwen3VLForConditionalGeneration, config, out, QWEN3VL_INIT_STD)


def build_vla_jepa(
    out: Path,
    qwen: Path,
    image: int = 64,
    state: int = 8,
    action: int = 7,
    cams: tuple[str, ...] = ("agentview",),
) -> Path:
    """lerobot's VLA-JEPA (random weights) on the toy Qwen3-VL folder ``qwen``: no world model,
    chunks of 4, 3 flow-matching steps, a two-layer DiT (cross- then self-attention) 32 wide,
    float32, short action / embodied token runs in the prompt. lerobot's default postprocessor
    (clip, pre-snap gripper, unnormalize, binarize gripper) is kept."""
    from lerobot.policies.vla_jepa.configuration_vla_jepa import VLAJEPAConfig
    from lerobot.policies.vla_jepa.modeling_vla_jepa import VLAJEPAPolicy

    inputs, outputs = _features(image, state, action, cams)
    cfg = VLAJEPAConfig(
        qwen_model_name=str(qwen),
        enable_world_model=False,
        torch_dtype="float32",
        input_features=inputs,
        output_features=outputs,
        chunk_size=4,
        n_action_steps=4,
        num_inference_timesteps=3,
        # Prompt: (num_video_frames // jepa_tubelet_size - 1) steps x 2 action tokens, 4 embodied.
        num_video_frames=4,
        jepa_tubelet_size=2,
        num_action_tokens_per_timestep=2,
        num_embodied_action_tokens_per_instruction=4,
        action_model_type="DiT-test",
        action_hidden_size=32,
        action_num_layers=2,
        action_num_heads=2,
        action_attention_head_dim=16,
        action_dropout=0.0,
        repeated_diffusion_steps=1,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = VLAJEPAPolicy(cfg).eval()
    with torch.no_grad():  # no layer may silence its inputs (none is zero-initialized today)
        for param in policy.model.action_model.parameters():
            if param.dim() >= 2 and not param.any():
                param.normal_(0.0, 0.2)
    return save_checkpoint(policy, cfg, _stats(image, state, action, cams), out)
