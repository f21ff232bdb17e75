"""Toy local VLM folders and the lerobot policies built on them, with no hub: random weights at
toy widths, a byte-level BPE tokenizer trained offline on a few sentences with the model's
special tokens, and the processor files its loader reads.

- Qwen2.5-VL (a hand-written Qwen-style chat template, the image and video processor configs):
  EO1's ``vlm_base`` instead of ``Qwen/Qwen2.5-VL-3B-Instruct``;
- InternVL3 (transformers' own InternVL classes, no remote code; EVO1 writes its prompt and
  preprocesses its images itself): EVO1's ``vlm_model_name``.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import torch

from training.toy_checkpoints import _features, _stats, save_checkpoint

# ----------------------------------------------------------------------------------------------
# Toy sizes
# ----------------------------------------------------------------------------------------------
PATCH_SIZE = 8  # vision patch size (real Qwen2.5-VL: 14)
MERGE_SIZE = 2  # spatial merge (same as real)
TEMPORAL_PATCH_SIZE = 2  # same as real
FACTOR = PATCH_SIZE * MERGE_SIZE  # images are resized to multiples of this
MIN_PIXELS = 16 * 16  # 64x64 camera frames get resized down to 32x32 ...
MAX_PIXELS = 32 * 32  # ... -> grid (1, 4, 4) = 16 patches = 4 image tokens per image
TEXT_HIDDEN = 64
TEXT_HEADS = 4  # head_dim 16 -> rotary half-dim 8 = sum(mrope_section)
MROPE_SECTION = [2, 3, 3]

# Qwen2.5-VL special tokens, in the order of the real tokenizer (151643..151656).
QWEN_SPECIAL_TOKENS = [
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<|object_ref_start|>",
    "<|object_ref_end|>",
    "<|box_start|>",
    "<|box_end|>",
    "<|quad_start|>",
    "<|quad_end|>",
    "<|vision_start|>",
    "<|vision_end|>",
    "<|vision_pad|>",
    "<|image_pad|>",
    "<|video_pad|>",
]

# Hand-written chat template that renders like Qwen2.5-VL's: each message becomes
# "<|im_start|>{role}\n...<|im_end|>\n", image parts become <|vision_start|><|image_pad|><|vision_end|>.
CHAT_TEMPLATE = (
    "{% set image_count = namespace(value=0) %}{% set video_count = namespace(value=0) %}"
    "{% for message in messages %}"
    "{% if loop.first and message['role'] != 'system' %}<|im_start|>system\nYou are a helpful assistant.<|im_end|>\n{% endif %}"
    "<|im_start|>{{ message['role'] }}\n"
    "{% if message['content'] is string %}{{ message['content'] }}<|im_end|>\n"
    "{% else %}"
    "{% for content in message['content'] %}"
    "{% if content['type'] == 'image' or 'image' in content or 'image_url' in content %}"
    "{% set image_count.value = image_count.value + 1 %}"
    "{% if add_vision_id %}Picture {{ image_count.value }}: {% endif %}"
    "<|vision_start|><|image_pad|><|vision_end|>"
    "{% elif content['type'] == 'video' or 'video' in content %}"
    "{% set video_count.value = video_count.value + 1 %}"
    "{% if add_vision_id %}Video {{ video_count.value }}: {% endif %}"
    "<|vision_start|><|video_pad|><|vision_end|>"
    "{% elif 'text' in content %}{{ content['text'] }}"
    "{% endif %}"
    "{% endfor %}<|im_end|>\n"
    "{% endif %}"
    "{% endfor %}"
    "{% if add_generation_prompt %}<|im_start|>assistant\n{% endif %}"
)

# Same pre-tokenizer regex as transformers' Qwen2Tokenizer.
QWEN_PRETOKENIZE_REGEX = r"""(?i:'s|'t|'re|'ve|'m|'ll|'d)|[^\r\n\p{L}\p{N}]?\p{L}+|\p{N}| ?[^\s\p{L}\p{N}]+[\r\n]*|\s*[\r\n]+|\s+(?!\S)|\s+"""
TOY_CORPUS = [
    "You are a helpful physical assistant.",
    "Image-1: Image-2: Image-3:",
    "You are a helpful assistant.",
    "pick it",
    "place it",
    "pick up the red block and place it in the bowl",
    "open the drawer, close the drawer, push the button",
    "system user assistant",
]


def _train_toy_tokenizer(
    specials: list[str] = QWEN_SPECIAL_TOKENS, vocab_size: int = 320, **kwargs: object
):
    """Train a tiny byte-level BPE with Qwen's pre-tokenizer and wrap it as a Qwen2Tokenizer,
    with ``specials`` added after the BPE vocabulary (as Qwen's tokenizer numbers them);
    ``kwargs`` go to the Qwen2Tokenizer."""
    from tokenizers import (
        AddedToken,
        Regex,
        Tokenizer,
        decoders,
        models,
        normalizers,
        pre_tokenizers,
        trainers,
    )
    from transformers import Qwen2Tokenizer

    tok = Tokenizer(models.BPE())
    tok.normalizer = normalizers.NFC()
    tok.pre_tokenizer = pre_tokenizers.Sequence(
        [
            pre_tokenizers.Split(Regex(QWEN_PRETOKENIZE_REGEX), behavior="isolated", invert=False),
            pre_tokenizers.ByteLevel(add_prefix_space=False, use_regex=False),
        ]
    )
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),  # all 256 bytes -> no unknown tokens
        special_tokens=[],
        show_progress=False,
    )
    tok.train_from_iterator(TOY_CORPUS, trainer=trainer)
    model_json = json.loads(tok.to_str())["model"]
    vocab = model_json["vocab"]
    merges = [
        tuple(m) if isinstance(m, list) else tuple(m.split(" ")) for m in model_json["merges"]
    ]

    qwen_tok = Qwen2Tokenizer(
        vocab=vocab,
        merges=merges,
        unk_token=None,
        bos_token=None,
        eos_token="<|im_end|>",
        pad_token="<|endoftext|>",
        model_max_length=4096,
        **kwargs,
    )
    # Specials get consecutive ids right after the BPE vocab, like the real Qwen tokenizer.
    qwen_tok.add_tokens([AddedToken(t, special=True, normalized=False) for t in specials])
    return qwen_tok


def toy_tokenizer_and_ids(specials: list[str] = QWEN_SPECIAL_TOKENS, **kwargs: object):
    """The toy tokenizer and the ids of its special tokens (each its own)."""
    tokenizer = _train_toy_tokenizer(specials, **kwargs)
    ids = {t: tokenizer.convert_tokens_to_ids(t) for t in specials}
    assert len(set(ids.values())) == len(specials), ids
    return tokenizer, ids


def fresh_dir(out: str | Path) -> Path:
    """``out``, emptied: no stale files from an earlier layout."""
    out = Path(out)
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    return out


def qwen_text_config(
    ids: dict[str, int], vocab_size: int, hidden: int, heads: int, **extra: object
) -> dict:
    """A two-layer Qwen-family text model at toy widths, padded and ended by Qwen's tokens."""
    return dict(
        vocab_size=vocab_size,
        hidden_size=hidden,
        intermediate_size=2 * hidden,
        num_hidden_layers=2,
        num_attention_heads=heads,
        num_key_value_heads=2,
        max_position_embeddings=1024,
        bos_token_id=None,
        eos_token_id=ids["<|im_end|>"],
        pad_token_id=ids["<|endoftext|>"],
        tie_word_embeddings=False,
        **extra,
    )


def qwen_vision_token_ids(ids: dict[str, int]) -> dict[str, int]:
    """The vision special tokens' ids, as a Qwen-VL config names them."""
    return dict(
        image_token_id=ids["<|image_pad|>"],
        video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"],
        vision_end_token_id=ids["<|vision_end|>"],
    )


def save_random(model_cls: type, config: object, out: Path, std: float = 0.02) -> Path:
    """``model_cls(config)`` with seed-0 random weights saved to ``out``. No weight matrix may
    be all zero (InternViT zero-initializes its cls token and position embeddings); biases
    stay as initialized."""
    torch.manual_seed(0)
    model = model_cls(config).to(torch.float32)
    with torch.no_grad():
        for param in model.parameters():
            if param.dim() >= 2 and not param.any():
                param.normal_(0.0, std)
    model.save_pretrained(out)
    return out


def build_qwen25vl_folder(out: str | Path) -> Path:
    """Write a random-weight toy Qwen2.5-VL checkpoint + every processor file into `out`."""
    from transformers import (
        Qwen2_5_VLConfig,
        Qwen2_5_VLForConditionalGeneration,
        Qwen2VLImageProcessor,
        Qwen2VLVideoProcessor,
    )

    out = fresh_dir(out)

    # 1) Tokenizer.
    tokenizer, ids = toy_tokenizer_and_ids()

    # 2) Image / video processors (Qwen2VL*), small pixel budget and matching patch geometry.
    vision_kwargs = dict(
        min_pixels=MIN_PIXELS,
        max_pixels=MAX_PIXELS,
        patch_size=PATCH_SIZE,
        temporal_patch_size=TEMPORAL_PATCH_SIZE,
        merge_size=MERGE_SIZE,
    )
    image_processor = Qwen2VLImageProcessor(**vision_kwargs)
    video_processor = Qwen2VLVideoProcessor(**vision_kwargs)

    # Hub-style layout (like Qwen/Qwen2.5-VL-3B-Instruct): one file per component, rather than the
    # combined processor_config.json that `Qwen2_5_VLProcessor.save_pretrained` writes in transformers 5.
    image_processor.save_pretrained(out)  # -> preprocessor_config.json
    video_processor.save_pretrained(out)  # -> video_preprocessor_config.json
    tokenizer.save_pretrained(out)  # -> tokenizer.json + tokenizer_config.json
    (out / "chat_template.jinja").write_text(CHAT_TEMPLATE)

    # 3) Model config. Leave head-room for the 7 EO1 tokens that EO1QwenProcessorStep adds at load time.
    vocab_size = int(math.ceil((len(tokenizer) + 16) / 64) * 64)
    config = Qwen2_5_VLConfig(
        text_config=qwen_text_config(
            ids,
            vocab_size,
            TEXT_HIDDEN,
            TEXT_HEADS,
            rope_parameters={
                "rope_type": "default",
                "rope_theta": 10000.0,
                "mrope_section": MROPE_SECTION,
            },
        ),
        vision_config=dict(
            depth=1,
            hidden_size=32,
            intermediate_size=64,
            num_heads=2,
            in_channels=3,
            patch_size=PATCH_SIZE,
            spatial_merge_size=MERGE_SIZE,
            temporal_patch_size=TEMPORAL_PATCH_SIZE,
            window_size=2 * FACTOR,  # window (in merged tokens) = window_size // merge // patch = 2
            out_hidden_size=TEXT_HIDDEN,
            fullatt_block_indexes=[0],
        ),
        **qwen_vision_token_ids(ids),
        tie_word_embeddings=False,
    )
    return save_random(Qwen2_5_VLForConditionalGeneration, config, out)


def build_eo1(
    out: Path,
    vlm: Path,
    image: int = 64,
    state: int = 8,
    action: int = 7,
    cams: tuple[str, ...] = ("agentview",),
) -> Path:
    """lerobot's EO1 (random weights) on the toy Qwen2.5-VL folder ``vlm``: chunks of 4, 3
    denoising steps, float32, the toy pixel budget (a 64 px frame is 4 image tokens)."""
    from lerobot.policies.eo1.configuration_eo1 import EO1Config
    from lerobot.policies.eo1.modeling_eo1 import EO1Policy

    inputs, outputs = _features(image, state, action, cams)
    cfg = EO1Config(
        vlm_base=str(vlm),
        input_features=inputs,
        output_features=outputs,
        chunk_size=4,
        n_action_steps=4,
        num_denoise_steps=3,
        dtype="float32",
        device="cpu",
        image_min_pixels=MIN_PIXELS,
        image_max_pixels=MAX_PIXELS,
    )
    torch.manual_seed(0)
    policy = EO1Policy(cfg).eval()
    return save_checkpoint(policy, cfg, _stats(image, state, action, cams), out)


# -- InternVL3 (EVO1) ----------------------------------------------------------------------------
INTERNVL_IMAGE = 32  # the vision tower's input (real: 448); EVO1's image_resolution must equal it
INTERNVL_PATCH = 8  # (real: 14): 4 x 4 patches
INTERNVL_DOWNSAMPLE = 0.5  # pixel shuffle, as the real one: 2 x 2 = 4 tokens per image
INTERNVL_SEQ = int((INTERNVL_IMAGE // INTERNVL_PATCH) ** 2 * INTERNVL_DOWNSAMPLE**2)
INTERNVL_TEXT_HIDDEN = 64  # EVO1's embed_dim must equal it
# InternVL3-hf's added tokens (EVO1 hard-wires <img>, </img> and <IMG_CONTEXT>)
INTERNVL_SPECIAL_TOKENS = [
    "<|endoftext|>",
    "<|im_start|>",
    "<|im_end|>",
    "<img>",
    "</img>",
    "<IMG_CONTEXT>",
    "<quad>",
    "</quad>",
    "<ref>",
    "</ref>",
    "<box>",
    "</box>",
    "<video>",
]
IMAGENET_MEAN = [0.485, 0.456, 0.406]
IMAGENET_STD = [0.229, 0.224, 0.225]


def build_internvl3_folder(out: Path) -> Path:
    """A toy InternVL3-hf folder: InternViT (1 layer) + pixel-shuffle projector + Qwen2 text
    model (2 layers), its processor files (EVO1 reads only the tokenizer: it writes its prompt
    and normalizes its images itself)."""
    from transformers import (
        GotOcr2ImageProcessor,
        InternVLConfig,
        InternVLModel,
        InternVLProcessor,
        InternVLVideoProcessor,
    )

    out = fresh_dir(out)
    tokenizer, ids = toy_tokenizer_and_ids(
        INTERNVL_SPECIAL_TOKENS,
        padding_side="right",  # EVO1 pools each row's last real token: right padding
        extra_special_tokens={
            "start_image_token": "<img>",
            "end_image_token": "</img>",
            "context_image_token": "<IMG_CONTEXT>",
            "video_token": "<video>",
        },
    )
    size = {"height": INTERNVL_IMAGE, "width": INTERNVL_IMAGE}
    InternVLProcessor(
        image_processor=GotOcr2ImageProcessor(
            size=size, crop_to_patches=False, image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD
        ),
        tokenizer=tokenizer,
        video_processor=InternVLVideoProcessor(
            size=size, image_mean=IMAGENET_MEAN, image_std=IMAGENET_STD
        ),
        image_seq_length=INTERNVL_SEQ,
    ).save_pretrained(out)
    config = InternVLConfig(
        vision_config={
            "hidden_size": 32,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "intermediate_size": 64,
            "image_size": [INTERNVL_IMAGE, INTERNVL_IMAGE],
            "patch_size": [INTERNVL_PATCH, INTERNVL_PATCH],
            "norm_type": "layer_norm",
            "use_mean_pooling": True,
        },
        text_config=qwen_text_config(
            ids,
            int(math.ceil(len(tokenizer) / 64) * 64),
            INTERNVL_TEXT_HIDDEN,
            4,
            model_type="qwen2",
        ),
        image_token_id=ids["<IMG_CONTEXT>"],
        image_seq_length=INTERNVL_SEQ,
        downsample_ratio=INTERNVL_DOWNSAMPLE,
        vision_feature_layer=-1,
        vision_feature_select_strategy="default",
        tie_word_embeddings=False,
    )
    return save_random(InternVLModel, config, out)


def build_evo1(
    out: Path,
    vlm: Path,
    image: int = 64,
    state: int = 8,
    action: int = 7,
    cams: tuple[str, ...] = ("agentview",),
) -> Path:
    """lerobot's EVO1 (random weights) on the toy InternVL3 folder ``vlm``: chunks of 4, 3
    sampling steps, float32, no flash attention."""
    from lerobot.policies.evo1.configuration_evo1 import Evo1Config
    from lerobot.policies.evo1.modeling_evo1 import Evo1Policy

    inputs, outputs = _features(image, state, action, cams)
    cfg = Evo1Config(
        vlm_model_name=str(vlm),
        vlm_num_layers=None,
        vlm_dtype="float32",
        use_flash_attn=False,
        use_amp=False,
        image_resolution=(INTERNVL_IMAGE, INTERNVL_IMAGE),
        input_features=inputs,
        output_features=outputs,
        chunk_size=4,
        n_action_steps=4,
        num_inference_timesteps=3,
        embed_dim=INTERNVL_TEXT_HIDDEN,
        hidden_dim=64,
        state_hidden_dim=64,
        num_heads=4,
        num_layers=2,
        max_text_length=256,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = Evo1Policy(cfg).eval()
    return save_checkpoint(policy, cfg, _stats(image, state, action, cams), out)
