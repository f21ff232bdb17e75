"""IDR's processor steps in the base's pipelines: where they go, and the 3B rows they make."""

from __future__ import annotations

import json

import pytest
import torch

from tests.lerobot_policy_idr.conftest import load, make_idr, obs_batch

pytestmark = pytest.mark.slow


def _steps(folder, name: str) -> list[str]:
    return [s["registry_name"] for s in json.loads((folder / name).read_text())["steps"]]


def test_steps_are_placed_after_batching_and_after_the_normalizer(bases, tmp_path) -> None:
    for kind in ("act", "diffusion"):
        folder = make_idr(
            bases[kind], tmp_path / kind, "--mode", "diagnose", "--state-space", "normalized"
        )
        pre = _steps(folder, "policy_preprocessor.json")
        assert pre == [
            "rename_observations_processor",
            "to_batch_processor",
            "idr_counterfactual_batch",
            "device_processor",
            "normalizer_processor",
            "idr_state_intervention",
        ], (kind, pre)
        # physical refinement: the policy unnormalizes, so the postprocessor does not
        assert _steps(folder, "policy_postprocessor.json") == ["device_processor"]
    for space in ("raw", "centered"):  # both before the normalizer (centered: the default)
        args = ("--mode", "diagnose") if space == "centered" else ("--mode", "diagnose", "--state-space", space)  # fmt: skip
        folder = make_idr(bases["act"], tmp_path / space, *args)
        assert "idr_state_intervention" not in _steps(folder, "policy_preprocessor.json")
    norm = make_idr(
        bases["act"], tmp_path / "n", "--mode", "diagnose", "--refine-space", "normalized"
    )
    assert _steps(norm, "policy_postprocessor.json")[0] == "unnormalizer_processor"
    baseline = make_idr(bases["act"], tmp_path / "b", "--mode", "baseline")
    assert "idr_counterfactual_batch" not in _steps(baseline, "policy_preprocessor.json")


def test_the_three_thirds_hold_factual_black_image_and_mean_state(bases, tmp_path) -> None:
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors

    folder = make_idr(bases["act"], tmp_path / "idr", "--mode", "diagnose")
    _, pre, _ = load(folder)
    base_pre, _ = make_pre_post_processors(
        PreTrainedConfig.from_pretrained(bases["act"]), pretrained_path=str(bases["act"])
    )
    obs = obs_batch(2)
    black = dict(obs, **{"observation.images.agentview": torch.zeros(2, 3, 64, 64)})
    out, factual, no_img = pre(dict(obs)), base_pre(dict(obs)), base_pre(black)
    img, state = out["observation.images.agentview"], out["observation.state"]
    assert img.shape[0] == state.shape[0] == 6 and out["idr_batch_size"] == 2
    assert out["task"] == obs["task"] * 3
    assert torch.equal(img[:2], factual["observation.images.agentview"])
    assert torch.equal(img[2:4], no_img["observation.images.agentview"])  # raw black, normalized
    assert torch.equal(img[4:], factual["observation.images.agentview"])
    assert torch.equal(state[:4], torch.cat([factual["observation.state"]] * 2))
    assert torch.equal(state[4:], torch.zeros(2, 8))  # normalized zero = the dataset mean


@pytest.mark.parametrize("space", ["centered", "normalized", "raw"])
def test_do_s_under_min_max_is_the_dataset_mean_only_when_centered(bases, tmp_path, space) -> None:
    """Diffusion normalizes its state MIN_MAX: ``normalized``'s zero is the middle of the
    range, ``raw``'s the physical origin; ``centered`` gives the dataset mean, as under
    MEAN_STD, so every architecture gets the same counterfactual state."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot_policy_idr.runtime import state_mean

    base = bases["diffusion"]
    folder = make_idr(base, tmp_path / space, "--mode", "diagnose", "--state-space", space)
    _, pre, _ = load(folder)
    base_pre, _ = make_pre_post_processors(
        PreTrainedConfig.from_pretrained(base), pretrained_path=str(base)
    )
    mean = torch.from_numpy(state_mean(base_pre.steps))
    obs = obs_batch(2)
    out = pre(dict(obs))["observation.state"][4:]
    at_mean = base_pre(dict(obs, **{"observation.state": mean.expand(2, -1).clone()}))
    at_origin = base_pre(dict(obs, **{"observation.state": torch.zeros(2, 8)}))
    want = {
        "centered": at_mean["observation.state"],
        "normalized": torch.zeros(2, 8),
        "raw": at_origin["observation.state"],
    }
    assert torch.equal(out, want[space])
    assert not torch.equal(want["centered"], want["normalized"])  # MIN_MAX: mean != midrange
    step = next(s for s in pre.steps if type(s).__name__ == "IDRCounterfactualBatchStep")
    assert (step.get_config()["state_mean"] is not None) == (space == "centered")  # recorded


@pytest.mark.parametrize("kind", ["pi05", "pi0"])
def test_pi_pipelines_get_three_consistent_thirds(tmp_path, monkeypatch, kind) -> None:
    """pi0 tokenizes the task before its normalizer, pi0.5 turns the normalized state into
    text tokens after it: wherever the steps sit, every tensor reaching the model has 3B rows,
    do(V) leaves the tokens alone and, for pi0.5, do(S) reaches the state's tokens."""
    from training.toy_checkpoints import (
        build_local_tokenizer,
        build_pi,
        tiny_pi_gemma,
    )

    tiny_pi_gemma(monkeypatch)
    tok = build_local_tokenizer(tmp_path / "tok", ["pick it", "place it"])
    base = build_pi(kind, tmp_path / kind, tok, monkeypatch)
    folder = make_idr(base, tmp_path / "idr", "--mode", "diagnose", "--state-space", "normalized")
    pre_steps = _steps(folder, "policy_preprocessor.json")
    norm = pre_steps.index("normalizer_processor")
    assert pre_steps.index("idr_state_intervention") == norm + 1, pre_steps
    _, pre, _ = load(folder)
    g = torch.Generator().manual_seed(0)
    obs = {
        "observation.images.agentview": torch.rand(2, 3, 32, 32, generator=g),
        "observation.images.wrist": torch.rand(2, 3, 32, 32, generator=g),
        "observation.state": torch.rand(2, 8, generator=g),
        "task": ["pick it", "place it"],
    }
    out = pre(obs)
    tensors = {k: v for k, v in out.items() if isinstance(v, torch.Tensor) and v.ndim}
    assert tensors and all(v.shape[0] == 6 for v in tensors.values()), {
        k: tuple(v.shape) for k, v in tensors.items()
    }
    tokens = next(v for k, v in tensors.items() if k.endswith("language.tokens"))
    assert torch.equal(tokens[:2], tokens[2:4])  # do(V): same words
    if kind == "pi05":  # the state is text: do(S) changed the tokens of rows 2B:3B
        assert not torch.equal(tokens[:2], tokens[4:])
    else:
        assert torch.equal(tokens[:2], tokens[4:])
        assert torch.equal(out["observation.state"][4:], torch.zeros(2, 8))


def test_an_observation_that_does_not_fit_the_base_is_refused_before_the_first_chunk(
    bases, tmp_path
) -> None:
    folder = make_idr(bases["act"], tmp_path / "idr", "--mode", "diagnose")
    _, pre, _ = load(folder)
    obs = obs_batch(1)
    wrong_cam = {"observation.images.front": obs.pop("observation.images.agentview"), **obs}
    with pytest.raises(ValueError, match=r"reads 'observation.images.agentview'.*--rename_map"):
        pre(wrong_cam)
    _, pre, _ = load(folder)
    short_state = {**obs_batch(1), "observation.state": torch.rand(1, 6)}
    with pytest.raises(ValueError, match=r"gives 6 dims, the base reads 8"):
        pre(short_state)
