"""The lerobot adapter on real pi0 / pi0.5 classes built offline, with a local tokenizer.

Nothing downloads: HF_HUB_OFFLINE=1 and any socket connect fails. The checkpoints use the
gemma_300m variants shrunk in-process (see ``tiny_pi_gemma``: lerobot 0.6.1 cannot run the
real gemma_300m pair, and ~1.9B parameters would not fit a CI test), random weights, the real
PI0Policy / PI05Policy code paths and their real saved pre/post processors.
"""

from __future__ import annotations

import json
import socket

import pytest
import torch
from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig

from training.toy_checkpoints import build_local_tokenizer, build_pi, tiny_pi_gemma
from workers.backbones.base import Observation
from workers.policy.wrapper import IDRWrapper

pytestmark = pytest.mark.slow

KINDS = ("pi05", "pi0")
INSTRUCTIONS = ["pick up the red block", "open the top drawer of the cabinet"]
CHUNK = 4


@pytest.fixture(scope="module")
def env(tmp_path_factory):
    """Offline, one torch thread, tiny gemma: active for the whole module (build and load)."""
    with pytest.MonkeyPatch.context() as mp:
        import huggingface_hub.constants

        mp.setenv("HF_HUB_OFFLINE", "1")
        mp.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)

        def no_network(*args, **kwargs):
            raise RuntimeError(f"network access in an offline test: {args}")

        mp.setattr(socket.socket, "connect", no_network)
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        tiny_pi_gemma(mp)
        root = tmp_path_factory.mktemp("pi")
        tok = build_local_tokenizer(root / "tokenizer", INSTRUCTIONS)
        yield {"root": root, "tokenizer": tok, "mp": mp}
        torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def ckpts(env):
    return {k: build_pi(k, env["root"] / k, env["tokenizer"], env["mp"]) for k in KINDS}


@pytest.fixture(scope="module")
def backbones(ckpts):
    from workers.backbones.lerobot import LerobotBackbone

    # exactly what backbone.params.path={folder} does
    return {k: LerobotBackbone(str(p)) for k, p in ckpts.items()}


def _obs(b: int = 2, seed: int = 0, instructions: list[str] | None = None) -> Observation:
    g = torch.Generator().manual_seed(seed)
    return Observation(
        {cam: torch.rand(b, 3, 32, 32, generator=g) for cam in ("agentview", "wrist")},
        0.5 + torch.rand(b, 8, generator=g),
        instructions or [INSTRUCTIONS[i % 2] for i in range(b)],
    )


def _step_index(pipeline, name: str) -> int:
    (i,) = [i for i, s in enumerate(pipeline.steps) if type(s).__name__ == name]
    return i


def _record_after(pipeline, index: int) -> list:
    from lerobot.lerobot_types import TransitionKey

    seen = []

    def hook(i, transition):
        if i == index:
            obs = transition[TransitionKey.OBSERVATION]
            rec = {k: v.clone() for k, v in obs.items() if torch.is_tensor(v)}
            rec["task"] = list(transition[TransitionKey.COMPLEMENTARY_DATA]["task"])
            seen.append(rec)

    pipeline.register_after_step_hook(hook)
    return seen


def _unhook(pipeline, n_before: int) -> None:
    del pipeline.after_step_hooks[n_before:]


@pytest.mark.parametrize("kind", KINDS)
def test_checkpoint_loads_offline_with_local_tokenizer(env, ckpts, backbones, kind) -> None:
    from safetensors.torch import load_file

    path = ckpts[kind]
    assert json.loads((path / "config.json").read_text())["type"] == kind
    pre = json.loads((path / "policy_preprocessor.json").read_text())
    (tok_step,) = [s for s in pre["steps"] if s.get("registry_name") == "tokenizer_processor"]
    assert tok_step["config"]["tokenizer_name"] == str(env["tokenizer"])

    bb = backbones[kind]
    assert bb.name == f"lerobot:{kind}" and bb.crn_mode == "shared_noise" and bb.can_batch
    assert bb.cameras == ("agentview", "wrist") and bb.state_dim == 8 and bb.action_dim == 7
    assert bb.chunk_len == CHUNK
    # the saved weights were loaded (pi's from_pretrained only prints when loading fails)
    saved = load_file(path / "model.safetensors")
    loaded = bb.policy.state_dict()
    assert all(torch.equal(loaded[k], v) for k, v in saved.items())
    noise = bb.make_noise(3, seed=1)
    assert noise.shape == (3, CHUNK, 8)  # (B, chunk_size, max_action_dim)
    out = bb.predict_chunk(_obs(3), noise)
    assert out.shape == (3, CHUNK, 7) and out.dtype == torch.float32 and torch.isfinite(out).all()


@pytest.mark.parametrize("kind", KINDS)
def test_batched_3b_equals_three_calls_with_shared_noise(backbones, kind) -> None:
    bb = backbones[kind]
    obs = _obs(2)
    noise = bb.make_noise(2, seed=11)
    same = [bb.predict_chunk(obs, noise) for _ in range(2)]
    assert torch.equal(same[0], same[1])  # shared noise, same inputs: no sampling difference
    other = bb.predict_chunk(obs, bb.make_noise(2, seed=12))
    assert (other - same[0]).abs().max() > 1e-4  # the noise is really used

    seen = []
    orig = bb.policy.predict_action_chunk
    bb.policy.predict_action_chunk = lambda batch, noise=None: (
        seen.append(noise) or orig(batch, noise=noise)
    )
    try:
        cfg = RefinerConfig(mode="E", tau=1e9)
        a = IDRWrapper(bb, cfg, batched=True).infer(obs, step_seed=3)
        b = IDRWrapper(bb, cfg, batched=False).infer(obs, step_seed=3)
    finally:
        del bb.policy.predict_action_chunk
    assert a.batched and a.crn and b.crn and not b.batched
    n3, *three = seen  # one 3B forward, then three B forwards, all with the same noise
    assert n3.shape == (6, CHUNK, 8) and len(three) == 3
    assert torch.equal(n3[:2], n3[2:4]) and torch.equal(n3[:2], n3[4:])
    assert all(torch.equal(n, n3[:2]) for n in three)
    for k in ("a_base", "a_no_img", "a_no_prop", "action"):
        torch.testing.assert_close(getattr(a, k), getattr(b, k), rtol=1e-4, atol=1e-4)
    assert a.diag.e_img.min() > 0 and a.diag.e_prop.min() > 0  # both modalities matter


@pytest.mark.parametrize("kind", KINDS)
def test_image_zeroed_raw_and_state_zeroed_after_normalizer(backbones, kind) -> None:
    bb = backbones[kind]
    pre = bb.pre
    norm = _step_index(pre, "NormalizerProcessorStep")
    assert norm == bb._normalizer_index
    n_hooks = len(pre.after_step_hooks)
    after_norm = _record_after(pre, norm)
    after_all = _record_after(pre, len(pre.steps) - 1)
    if kind == "pi05":
        state_tok = _step_index(pre, "Pi05PrepareStateTokenizerProcessorStep")
        assert norm < state_tok  # do(S) in the normalizer hook precedes the state tokens
        after_state_tok = _record_after(pre, state_tok)
    pixels, state_in = [], []
    tower = bb.policy.model.paligemma_with_expert.paligemma.model.vision_tower
    h1 = tower.register_forward_pre_hook(
        lambda m, args, kw: pixels.append((args[0] if args else kw["pixel_values"]).clone()),
        with_kwargs=True,
    )
    h2 = None
    if kind == "pi0":  # pi0 feeds the state tensor to state_proj
        h2 = bb.policy.model.state_proj.register_forward_pre_hook(
            lambda m, args: state_in.append(args[0].clone())
        )
    try:
        IDRWrapper(
            bb,
            RefinerConfig(mode="diagnose"),
            InterventionConfig(state_space="normalized"),
            batched=True,
        ).infer(_obs(2))
    finally:
        h1.remove()
        if h2 is not None:
            h2.remove()
        _unhook(pre, n_hooks)

    # rows: factual 0:2, do(V) 2:4, do(S) 4:6
    state = after_norm[-1]["observation.state"]
    assert state.shape == (6, 8)
    assert torch.equal(state[4:], torch.zeros(2, 8))  # zero in normalized space
    assert (state[:4].abs() > 0).all()
    torch.testing.assert_close(state[:2], state[2:4])  # do(V) leaves the state alone
    for cam in ("agentview", "wrist"):
        img = after_all[-1][f"observation.images.{cam}"]  # VISUAL is IDENTITY for pi
        assert torch.equal(img[2:4], torch.zeros_like(img[2:4]))  # black raw [0, 1] image
        assert img[[0, 1, 4, 5]].min() >= 0 and img[[0, 1, 4, 5]].max() > 0
    assert len(pixels) == 2  # one SigLIP call per camera, on the whole 3B batch
    for px in pixels:
        assert px.shape == (6, 3, 28, 28)  # resized to image_resolution
        assert torch.equal(px[2:4], torch.full_like(px[2:4], -1.0))  # black is -1 for SigLIP
        assert (px[[0, 1, 4, 5]] > -1).any()
    if kind == "pi05":  # the zero reaches the prompt as bin 128, only on the do(S) rows
        tasks = after_state_tok[-1]["task"]
        zero_bins = "State: " + " ".join(["128"] * 8) + ";"
        assert all(zero_bins in t for t in tasks[4:]) and not any(zero_bins in t for t in tasks[:4])
        assert tasks[0] == tasks[2] and tasks[0].startswith(f"Task: {INSTRUCTIONS[0]}, State: ")
    else:
        assert torch.equal(state_in[-1][4:], torch.zeros(2, 8))


@pytest.mark.parametrize("kind", KINDS)
def test_instruction_goes_through_local_tokenizer(env, backbones, kind) -> None:
    from transformers import AutoTokenizer

    bb = backbones[kind]
    pre = bb.pre
    tok_index = _step_index(pre, "TokenizerProcessorStep")
    n_hooks = len(pre.after_step_hooks)
    seen = _record_after(pre, tok_index)
    obs = _obs(2, instructions=[INSTRUCTIONS[0]] * 2)
    noise = bb.make_noise(2, seed=4)
    try:
        a = bb.predict_chunk(obs, noise)
        b = bb.predict_chunk(_obs(2, instructions=[INSTRUCTIONS[1]] * 2), noise)
    finally:
        _unhook(pre, n_hooks)
    local = AutoTokenizer.from_pretrained(str(env["tokenizer"]))
    ids = [s["observation.language.tokens"] for s in seen]
    masks = [s["observation.language.attention_mask"] for s in seen]
    for rec, i in zip(seen, ids, strict=True):
        want = local(rec["task"], max_length=32, padding="max_length", truncation=True)
        assert i.tolist() == want["input_ids"]  # the local tokenizer made these ids
        assert (i[:, 0] == local.bos_token_id).all()
        assert (i != local.unk_token_id).all()  # every word known to the local vocabulary
    assert not torch.equal(ids[0], ids[1]) and masks[0].sum() != masks[1].sum()
    assert (a - b).abs().max() > 1e-4  # the instruction changes the actions
