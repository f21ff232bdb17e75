"""Toy lerobot checkpoints: small real lerobot policies (random weights) built offline from
their configs and saved as checkpoints, for the tests and the benchmarks (no hub, no training).

lerobot's classes and code paths at toy widths; ``full_size`` in ``build_act`` keeps lerobot's
default widths (the benchmarks time those). The X-VLA one: ``training.toy_xvla_checkpoint``."""

from __future__ import annotations

from pathlib import Path

import torch
from idr_core.features import ACTION, IMAGE_PREFIX, OBS_IMAGE, OBS_STATE


def _image_key(cam: str) -> str:
    """``image!``: lerobot's one-camera key ``observation.image`` (PushT), else
    ``observation.images.<cam>``."""
    return OBS_IMAGE if cam == "image!" else f"{IMAGE_PREFIX}{cam}"


def _features(image: int | tuple[int, int], state: int, action: int, cams: tuple[str, ...]):
    """``image``: a square size in px, or (height, width)."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    hw = (image, image) if isinstance(image, int) else tuple(image)
    inputs = {_image_key(c): PolicyFeature(FeatureType.VISUAL, (3, *hw)) for c in cams}
    inputs[OBS_STATE] = PolicyFeature(FeatureType.STATE, (state,))
    return inputs, {ACTION: PolicyFeature(FeatureType.ACTION, (action,))}


def _stats(image: int | tuple[int, int], state: int, action: int, cams: tuple[str, ...]) -> dict:
    g = torch.Generator().manual_seed(0)
    stats = {
        OBS_STATE: {
            "mean": torch.rand(state, generator=g),
            "std": 0.5 + torch.rand(state, generator=g),
            "min": -torch.ones(state),
            "max": torch.ones(state),
        },
        ACTION: {
            "mean": torch.rand(action, generator=g),
            "std": 0.5 + torch.rand(action, generator=g),
            "min": -torch.ones(action),
            "max": torch.ones(action),
        },
    }
    for c in cams:
        stats[_image_key(c)] = {
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
    image: int | tuple[int, int] = 64,
    state: int = 8,
    action: int = 7,
    chunk: int = 10,
    cams: tuple[str, ...] = ("agentview",),
    n_action_steps: int | None = None,
    full_size: bool = False,
) -> Path:
    """``full_size``: lerobot's default widths and depths (for benchmarks), else tiny ones."""
    from lerobot.policies.act.configuration_act import ACTConfig
    from lerobot.policies.act.modeling_act import ACTPolicy

    inputs, outputs = _features(image, state, action, cams)
    small = {
        "dim_model": 64,
        "n_heads": 2,
        "dim_feedforward": 128,
        "n_encoder_layers": 1,
        "n_decoder_layers": 1,
    }
    cfg = ACTConfig(
        input_features=inputs,
        output_features=outputs,
        pretrained_backbone_weights=None,
        **({} if full_size else small),
        use_vae=False,
        chunk_size=chunk,
        n_action_steps=n_action_steps or chunk,
        device="cpu",
    )
    torch.manual_seed(0)
    return save_checkpoint(ACTPolicy(cfg).eval(), cfg, _stats(image, state, action, cams), out)


def build_diffusion(
    out: Path,
    image: int = 64,
    state: int = 8,
    action: int = 7,
    n_obs_steps: int = 1,
    cams: tuple[str, ...] = ("agentview",),
) -> Path:
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    inputs, outputs = _features(image, state, action, cams)
    cfg = DiffusionConfig(
        input_features=inputs,
        output_features=outputs,
        pretrained_backbone_weights=None,
        noise_scheduler_type="DDIM",
        num_inference_steps=3,
        down_dims=(32, 64),
        horizon=8,
        n_action_steps=4,
        n_obs_steps=n_obs_steps,
        crop_shape=None,
        device="cpu",
    )
    torch.manual_seed(0)
    return save_checkpoint(
        DiffusionPolicy(cfg).eval(), cfg, _stats(image, state, action, cams), out
    )


def build_vqbet(
    out: Path,
    image: int = 64,
    state: int = 8,
    action: int = 7,
    temperature: float = 0.1,
    cams: tuple[str, ...] = ("agentview",),
) -> Path:
    """A small VQ-BeT (random weights) whose residual VQ is marked trained (``discretized``, as
    its training's first phase leaves it), so its head decodes actions from codebook codes and
    offsets; 2 observation steps, chunks of 4. It samples its codes at ``temperature``
    (lerobot's default 0.1; near 0 its sampling is an argmax)."""
    from lerobot.policies.vqbet.configuration_vqbet import VQBeTConfig
    from lerobot.policies.vqbet.modeling_vqbet import VQBeTPolicy

    inputs, outputs = _features(image, state, action, cams)
    cfg = VQBeTConfig(
        input_features=inputs,
        output_features=outputs,
        pretrained_backbone_weights=None,
        crop_shape=None,
        n_obs_steps=2,
        n_action_pred_token=3,
        action_chunk_size=4,
        vqvae_n_embed=8,
        vqvae_embedding_dim=32,
        vqvae_enc_hidden_dim=32,
        gpt_block_size=100,
        gpt_n_layer=2,
        gpt_n_head=2,
        gpt_hidden_dim=64,
        gpt_input_dim=64,
        gpt_output_dim=64,
        spatial_softmax_num_keypoints=8,
        bet_softmax_temperature=temperature,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = VQBeTPolicy(cfg).eval()
    policy.vqbet.action_head.vqvae_model.discretized.fill_(True)
    return save_checkpoint(policy, cfg, _stats(image, state, action, cams), out)


def build_tiny_clip(out: Path, instructions: list[str]) -> Path:
    """A local CLIP folder at toy widths (random weights, 32 px images in 8 px patches) with a
    word-level tokenizer trained offline on ``instructions``: what Multi-Task DiT names as its
    vision and text encoder instead of a hub id (lerobot checks that the name says "clip")."""
    from transformers import CLIPConfig, CLIPModel

    if "clip" not in out.name.lower():
        raise ValueError(f"{out}: Multi-Task DiT requires 'clip' in the encoder's name")
    tok = build_local_tokenizer(out.parent / f"{out.name}-tokenizer", instructions)
    cfg = CLIPConfig(
        text_config={
            "vocab_size": 512,
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "max_position_embeddings": 16,
        },
        vision_config={
            "hidden_size": 32,
            "intermediate_size": 64,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "image_size": 32,
            "patch_size": 8,
        },
        projection_dim=32,
    )
    torch.manual_seed(0)
    CLIPModel(cfg).save_pretrained(out)
    for f in tok.iterdir():
        if f.name != "config.json":
            (out / f.name).write_bytes(f.read_bytes())
    return out


def build_multi_task_dit(
    out: Path, clip: Path, image: int = 64, state: int = 8, action: int = 7
) -> Path:
    """A small Multi-Task DiT (random weights; DDIM, 3 steps) on the local CLIP folder ``clip``:
    2 observation steps, chunks of 8 of which 4 execute, text conditioned."""
    from lerobot.policies.multi_task_dit.configuration_multi_task_dit import MultiTaskDiTConfig
    from lerobot.policies.multi_task_dit.modeling_multi_task_dit import MultiTaskDiTPolicy

    inputs, outputs = _features(image, state, action, ("agentview",))
    cfg = MultiTaskDiTConfig(
        input_features=inputs,
        output_features=outputs,
        vision_encoder_name=str(clip),
        text_encoder_name=str(clip),
        image_resize_shape=(32, 32),
        image_crop_shape=(32, 32),
        hidden_dim=32,
        num_layers=2,
        num_heads=2,
        timestep_embed_dim=32,
        horizon=8,
        n_action_steps=4,
        noise_scheduler_type="DDIM",
        num_train_timesteps=10,
        num_inference_steps=3,
        tokenizer_max_length=16,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = MultiTaskDiTPolicy(cfg).eval()
    with torch.no_grad():  # its DiT zero-initializes its conditioning and output layers (adaLN-
        for param in policy.parameters():  # zero): at init the output ignores every input
            if not param.any():
                param.normal_(0.0, 0.2)
    return save_checkpoint(policy, cfg, _stats(image, state, action, ("agentview",)), out)


# -- pi0 / pi0.5 -------------------------------------------------------------------------------
# lerobot 0.6.1 cannot run its smallest pi variant (paligemma_variant="gemma_300m"): the SigLIP
# projector is hard-wired to 2048-d while gemma_300m's language embeddings are 1024-d, so
# embed_prefix fails; with that fixed it would still be ~1.9B parameters (~66 s to build,
# ~9.5 GB RSS on CPU). The tests and the benchmarks' dry runs therefore shrink lerobot's gemma
# variant table and the PaliGemma vision config in-process (``tiny_pi_gemma``): same classes,
# same code paths, tiny widths. The patch must be active both when building and when loading a
# checkpoint.

PI_SPECIAL_TOKENS = ("<pad>", "<eos>", "<bos>", "<unk>")  # PaliGemma's ids 0, 1, 2, 3


def build_local_tokenizer(out: Path, instructions: list[str]) -> Path:
    """A word-level tokenizer trained offline on ``instructions`` and pi0.5's prompt words
    (state bins 0..255 included), with PaliGemma's special tokens and a leading <bos>."""
    from tokenizers import Tokenizer, models, pre_tokenizers, processors, trainers
    from transformers import PreTrainedTokenizerFast

    corpus = [*instructions, "Task: , State: ;\nAction: ", " ".join(map(str, range(256)))]
    tok = Tokenizer(models.WordLevel(unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.train_from_iterator(
        corpus, trainers.WordLevelTrainer(special_tokens=list(PI_SPECIAL_TOKENS))
    )
    tok.post_processor = processors.TemplateProcessing(
        single="<bos> $A", pair="<bos> $A $B", special_tokens=[("<bos>", 2)]
    )
    fast = PreTrainedTokenizerFast(
        tokenizer_object=tok,
        pad_token="<pad>",
        eos_token="<eos>",
        bos_token="<bos>",
        unk_token="<unk>",
    )
    fast.save_pretrained(out)
    return out


def tiny_pi_gemma(mp, width: int = 64, depth: int = 2) -> None:
    """Shrink pi0/pi0.5's gemma variants and SigLIP tower via ``mp`` (a pytest MonkeyPatch: the
    patch lasts until ``mp.undo()``).

    lerobot's joint attention hard-codes 8 heads (``1 * 8 * head_dim``): keep num_heads=8."""
    from lerobot.policies.pi0 import modeling_pi0
    from lerobot.policies.pi05 import modeling_pi05

    for mod in (modeling_pi0, modeling_pi05):
        gemma = mod.GemmaConfig(
            width=width,
            depth=depth,
            mlp_dim=2 * width,
            num_heads=8,
            num_kv_heads=1,
            head_dim=width // 8,
        )
        orig = mod.PaliGemmaForConditionalGenerationWithPiGemma

        def paligemma(config, _orig=orig):
            v = config.vision_config
            v.hidden_size, v.intermediate_size = 32, 64
            v.num_hidden_layers, v.num_attention_heads = 1, 2
            v.projection_dim = config.text_config.hidden_size  # lerobot's 2048 fits only gemma_2b
            return _orig(config=config)

        mp.setattr(mod, "get_gemma_config", lambda variant, _g=gemma: _g)
        mp.setattr(mod, "PaliGemmaForConditionalGenerationWithPiGemma", paligemma)


def _pi_stats(image: int, state: int, action: int, cams: tuple[str, ...]) -> dict:
    """``_stats`` plus the q01 / q99 quantiles pi0.5's QUANTILES normalizer reads."""
    stats = _stats(image, state, action, cams)
    g = torch.Generator().manual_seed(1)
    for key, dim in ((OBS_STATE, state), (ACTION, action)):
        stats[key]["q01"] = -0.5 - torch.rand(dim, generator=g)
        stats[key]["q99"] = 1.0 + torch.rand(dim, generator=g)
    return stats


def build_pi(
    kind: str,
    out: Path,
    tokenizer_dir: Path,
    mp,
    image: int = 32,
    resolution: int = 28,
    state: int = 8,
    action: int = 7,
    chunk: int = 4,
    cams: tuple[str, ...] = ("agentview", "wrist"),
) -> Path:
    """A random-weight pi0 (``kind="pi0"``) or pi0.5 (``"pi05"``) checkpoint at the gemma_300m
    variants (shrunk by ``tiny_pi_gemma``, which must be active), whose saved preprocessor names
    the local tokenizer folder instead of google/paligemma-3b-pt-224."""
    from lerobot.processor import TokenizerProcessorStep

    if kind == "pi05":
        from lerobot.policies.pi05 import processor_pi05 as proc
        from lerobot.policies.pi05.configuration_pi05 import PI05Config as Config
        from lerobot.policies.pi05.modeling_pi05 import PI05Policy as Policy
    elif kind == "pi0":
        from lerobot.policies.pi0 import processor_pi0 as proc
        from lerobot.policies.pi0.configuration_pi0 import PI0Config as Config
        from lerobot.policies.pi0.modeling_pi0 import PI0Policy as Policy
    else:
        raise ValueError(f"kind must be pi0 or pi05, not {kind!r}")
    inputs, outputs = _features(image, state, action, cams)
    cfg = Config(
        input_features=inputs,
        output_features=outputs,
        paligemma_variant="gemma_300m",
        action_expert_variant="gemma_300m",
        image_resolution=(resolution, resolution),
        chunk_size=chunk,
        n_action_steps=chunk,
        num_inference_steps=2,
        max_state_dim=state,
        max_action_dim=8,
        tokenizer_max_length=32,
        device="cpu",
    )
    with mp.context() as m:
        m.setattr(
            proc,
            "TokenizerProcessorStep",
            lambda tokenizer_name, **kw: TokenizerProcessorStep(
                tokenizer_name=str(tokenizer_dir), **kw
            ),
        )
        torch.manual_seed(0)
        policy = Policy(cfg).eval()
        return save_checkpoint(policy, cfg, _pi_stats(image, state, action, cams), out)


def build_act_ttt(out: Path, image: int = 64, state: int = 8, action: int = 7) -> Path:
    """lerobot-policy-act-ttt's ACT with test-time training (a real plugin from the package
    index, registered through lerobot's plugin discovery), at small widths, random weights."""
    from lerobot.configs import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    cams = ("agentview",)
    inputs, outputs = _features(image, state, action, cams)
    cfg = PreTrainedConfig.get_choice_class("act_ttt")(
        input_features=inputs, output_features=outputs, device="cpu",
        pretrained_backbone_weights=None, dim_model=64, n_heads=2, dim_feedforward=128,
        n_encoder_layers=1, n_decoder_layers=1, chunk_size=4, n_action_steps=4, use_vae=False,
        ttt_ss_head_latent_dim=16, ttt_steps=1, ttt_n_samples=2,
    )  # fmt: skip
    torch.manual_seed(0)
    policy = get_policy_class("act_ttt")(cfg)
    return save_checkpoint(policy, cfg, _stats(image, state, action, cams), out)


# -- SmolVLA -----------------------------------------------------------------------------------
def build_smolvla(
    out: Path,
    image: int = 96,
    state: int = 2,
    action: int = 2,
    chunk: int = 8,
    n_action_steps: int = 4,
    cams: tuple[str, ...] = ("image!",),
) -> Path:
    """A random-weight SmolVLA checkpoint built offline: lerobot's SmolVLA on the zoo's tiny
    SmolVLM2 (``checkpoints/zoo/hub/zoo-smolvlm2-tiny``: its config and processor, named by
    path, so no hub cache is read), 4 VLM and expert layers, 4 flow-matching steps."""
    from lerobot.policies.smolvla.configuration_smolvla import SmolVLAConfig
    from lerobot.policies.smolvla.modeling_smolvla import SmolVLAPolicy

    from training.zoo_hub import HUB_DIR, SMOLVLM

    inputs, outputs = _features(image, state, action, cams)
    cfg = SmolVLAConfig(
        input_features=inputs,
        output_features=outputs,
        vlm_model_name=str(HUB_DIR / SMOLVLM),
        load_vlm_weights=False,
        resize_imgs_with_padding=(image, image),
        tokenizer_max_length=16,
        num_vlm_layers=4,
        num_expert_layers=4,
        num_steps=4,
        chunk_size=chunk,
        n_action_steps=n_action_steps,
        max_state_dim=8,
        max_action_dim=7,
        device="cpu",
    )
    torch.manual_seed(0)
    policy = SmolVLAPolicy(cfg).eval()
    return save_checkpoint(policy, cfg, _stats(image, state, action, cams), out)
