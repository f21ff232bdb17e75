"""The idr policy on real lerobot policies (ACT, Diffusion under DDIM; random weights, offline):
baseline is the base bit for bit, diagnose executes the base row of the three-pass forward,
E is the harness's IDR exactly, and the hardware safety rules hold."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from idr_core.sidecar import read_sidecar

from tests.lerobot_policy_idr.conftest import load, make_idr, obs_batch, rollout

pytestmark = pytest.mark.slow


def _base(path):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    cfg = PreTrainedConfig.from_pretrained(path)
    policy = get_policy_class(cfg.type).from_pretrained(path, config=cfg).eval()
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(path))
    return policy, pre, post


def _harness(base, tau: float, mode: str = "E"):
    """idr-eval's IDRWrapper around its lerobot backbone of ``base``, mode ``mode``, on the
    runtime's defaults, which are the plugin's (do(S) centered, refined actions clipped)."""
    from idr_core.refiner import RefinerConfig

    from workers.backbones.lerobot import LerobotBackbone
    from workers.policy.wrapper import IDRWrapper

    backbone = LerobotBackbone(str(base))
    policy = IDRWrapper(backbone, RefinerConfig(mode=mode, tau=tau))
    return backbone, policy


@pytest.mark.parametrize("kind", ["act", "diffusion"])
def test_baseline_is_the_base_bit_for_bit(bases, tmp_path, kind) -> None:
    folder = make_idr(
        bases[kind],
        tmp_path / "idr",
        "--mode",
        "baseline",
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    torch.manual_seed(0)
    theirs = rollout(*_base(bases[kind]), steps=9)
    torch.manual_seed(0)
    policy, pre, post = load(folder)
    ours = rollout(policy, pre, post, steps=9)
    for t, (a, b) in enumerate(zip(theirs, ours, strict=True)):
        assert torch.equal(a, b), f"step {t}: {a} vs {b}"
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    # one row per env per inference: the base replans every n_action_steps
    n_steps = policy.base.config.n_action_steps
    assert len(rows) == 2 * len(range(0, 9, n_steps))
    assert rows["e_img"].isna().all()  # baseline runs no counterfactual


def test_diagnose_executes_the_base_row_of_the_three_pass_forward(bases, tmp_path) -> None:
    folder = make_idr(
        bases["act"],
        tmp_path / "idr",
        "--mode",
        "diagnose",
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    theirs = rollout(*_base(bases["act"]), steps=8)
    policy, pre, post = load(folder)
    ours = rollout(policy, pre, post, steps=8)
    diff = max(float((a - b).abs().max()) for a, b in zip(theirs, ours, strict=True))
    # the same rows in a batch of 3B instead of B: equal up to float32 rounding of that batch
    assert diff < 1e-5, diff
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    assert len(rows) == 2 * 2 and (rows["e_img"] > 0).all() and (rows["e_prop"] > 0).all()
    assert set(rows["fallback"]) == {""} and (rows["clipped"] == 0).all()


def test_postprocessor_steps_before_the_unnormalizer_stay_in_the_normalized_space(
    bases, tmp_path
) -> None:
    """A base whose postprocessor acts on normalized actions before unnormalizing them (as
    VLA-JEPA snaps its gripper to {0, 1} there): IDR runs that step, then the unnormalizer, then
    refines, so diagnose executes the base's own actions (the snap applied to physical actions
    would give other ones)."""
    import shutil

    base = tmp_path / "clipping_act"
    shutil.copytree(bases["act"], base)
    post_json = base / "policy_postprocessor.json"
    post = json.loads(post_json.read_text())
    snap = {
        "registry_name": "vla_jepa_pre_snap_gripper",
        "config": {"gripper_dim": 6, "threshold": 0.0},
    }
    post["steps"].insert(0, snap)
    post_json.write_text(json.dumps(post))
    folder = make_idr(base, tmp_path / "idr", "--mode", "diagnose")
    theirs = rollout(*_base(base), steps=8)
    ours = rollout(*load(folder), steps=8)
    diff = max(float((a - b).abs().max()) for a, b in zip(theirs, ours, strict=True))
    assert diff < 1e-5, diff
    unsnapped = rollout(*_base(bases["act"]), steps=8)  # the snap changes these actions
    assert max(float((a - b).abs().max()) for a, b in zip(theirs, unsnapped, strict=True)) > 0.01


def test_postprocessor_steps_after_the_unnormalizer_apply_to_the_refined_chunk(
    bases, tmp_path
) -> None:
    """A base whose postprocessor changes physical actions after unnormalizing them (as
    VLA-JEPA binarizes its gripper): the plugin and idr-eval's backbone both measure and refine
    the unnormalized actions and apply that step to the refined chunk only, so mode E gives the
    same chunk and the same E_img both ways, and the executed gripper is binary."""
    import shutil

    from workers.backbones.base import Observation

    base = tmp_path / "binarizing_act"
    shutil.copytree(bases["act"], base)
    post_json = base / "policy_postprocessor.json"
    post = json.loads(post_json.read_text())
    names = [s["registry_name"] for s in post["steps"]]
    # its default settings (gripper dim 6, threshold 0.5): lerobot's step saves no config
    binarize = {"registry_name": "vla_jepa_binarize_gripper"}
    post["steps"].insert(names.index("unnormalizer_processor") + 1, binarize)
    post_json.write_text(json.dumps(post))
    folder = make_idr(base, tmp_path / "idr", "--tau", "1e9", "--diagnostics-dir", str(tmp_path))
    backbone, harness = _harness(base, 1e9)
    assert backbone.finish_chunk is not None
    policy, pre, post_ = load(folder)
    obs = obs_batch(2, seed=0)
    step = harness.infer(
        Observation(
            {"agentview": obs["observation.images.agentview"]},
            obs["observation.state"],
            obs["task"],
        )
    )
    with torch.inference_mode():
        ours = post_(policy.predict_action_chunk(pre(obs)))
    assert torch.equal(ours[:, : backbone.chunk_len], step.action)
    assert set(step.action[..., 6].unique().tolist()) <= {-1.0, 1.0}
    assert not set(step.a_base[..., 6].unique().tolist()) <= {-1.0, 1.0}  # measured before it
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path)
    diag = step.diag.to_numpy()
    for key in ("e_img", "e_prop", "r_img", "gate"):
        assert np.array_equal(rows[key].to_numpy()[-2:].astype(np.float32), diag[key]), key


@pytest.mark.parametrize(
    ("kind", "mode"),
    [
        ("act", "E"),
        ("diffusion", "E"),
        ("act", "random"),
        ("diffusion", "shuffled"),
        ("act", "scale_free"),
        ("diffusion", "cfg"),
    ],
)
def test_mode_equals_the_harness_exactly(bases, tmp_path, kind, mode) -> None:
    """The same checkpoint, observation, noise and placebo seed: the plugin's refined chunk and
    diagnostics equal idr-eval's IDRWrapper around its lerobot backbone, bit for bit, for E,
    its controls and image guidance."""
    from workers.backbones.base import Observation

    tau = "1e9"  # the gate on for every row: the refinement is exercised
    folder = make_idr(
        bases[kind],
        tmp_path / "idr",
        "--tau",
        tau,
        "--mode",
        mode,
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    backbone, harness = _harness(bases[kind], float(tau), mode)
    policy, pre, post = load(folder)
    for seed in range(3):
        obs = obs_batch(2, seed=seed)
        step = harness.infer(
            Observation(
                {"agentview": obs["observation.images.agentview"]},
                obs["observation.state"],
                obs["task"],
            ),
            step_seed=seed,
        )
        noise = backbone.make_noise(2, seed)
        policy.reset()
        with torch.inference_mode():
            ours = post(policy.predict_action_chunk(pre(obs), noise=noise, seed=seed))
        assert torch.equal(ours[:, : backbone.chunk_len], step.action), f"seed {seed}"
        assert not torch.equal(step.action, step.a_base)  # refined: the comparison is not vacuous
    if step.diag is None:  # cfg: no diagnostics without the do(S) pass
        return
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    diag = step.diag.to_numpy()
    for key in ("e_img", "e_prop", "r_img", "gate", "w_prop"):
        assert np.array_equal(rows[key].to_numpy()[-2:].astype(np.float32), diag[key]), key


def _patched(policy, fn) -> None:
    orig = policy.base.predict_action_chunk

    def predict(batch, **kw):
        return fn(orig(batch, **kw))

    policy.base.predict_action_chunk = predict


def test_refined_actions_stay_in_the_bases_bounds(bases, tmp_path) -> None:
    folder = make_idr(
        bases["act"],
        tmp_path / "idr",
        "--tau",
        "1e9",
        "--alpha",
        "40",
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    policy, pre, _ = load(folder)
    with torch.inference_mode():
        out = policy.predict_action_chunk(pre(obs_batch(2)))
    lo, hi = (torch.as_tensor(b) for b in policy._bounds)
    # the fixture's bounds are [-1, 1]; the base action itself may lie outside them
    policy_dx = make_idr(
        bases["act"],
        tmp_path / "diag",
        "--mode",
        "diagnose",
        "--diagnostics-dir",
        str(tmp_path / "d2"),
    )
    base_policy, base_pre, _ = load(policy_dx)
    with torch.inference_mode():
        a_base = base_policy.predict_action_chunk(base_pre(obs_batch(2)))
    assert (out >= torch.minimum(lo, a_base) - 1e-6).all()
    assert (out <= torch.maximum(hi, a_base) + 1e-6).all()
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    assert (rows["clipped"] > 0).all()  # alpha 40 pushes every row out: clipped and counted


def test_a_nonfinite_counterfactual_executes_the_base_action(bases, tmp_path) -> None:
    folder = make_idr(
        bases["act"], tmp_path / "idr", "--tau", "1e9", "--diagnostics-dir", str(tmp_path / "d")
    )
    policy, pre, _ = load(folder)

    def poison(out):  # the do(V) rows of the 3B forward become NaN
        out = out.clone()
        out[2:4] = float("nan")
        return out

    with torch.inference_mode():
        clean = policy.base.predict_action_chunk(pre(obs_batch(2)))
        _patched(policy, poison)
        out = policy.predict_action_chunk(pre(obs_batch(2)))
    assert torch.isfinite(out).all()
    assert torch.equal(out, policy._physical(clean[:2, : policy.n_action_steps]))
    policy.sidecar.flush()
    assert list(read_sidecar(tmp_path / "d")["fallback"]) == ["nonfinite"] * 2


def test_an_inference_past_its_deadline_executes_the_base_action(bases, tmp_path) -> None:
    folder = make_idr(
        bases["act"],
        tmp_path / "idr",
        "--tau",
        "1e9",
        "--deadline-ms",
        "0.001",
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    policy, pre, _ = load(folder)
    with torch.inference_mode():
        batch = pre(obs_batch(2))
        out = policy.predict_action_chunk(batch)
        base = policy._physical(
            policy.base.predict_action_chunk(batch)[:2, : policy.n_action_steps]
        )
    assert torch.equal(out, base)
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    assert list(rows["fallback"]) == ["deadline"] * 2 and (rows["inference_ms"] > 0.001).all()


def test_sidecar_rows_follow_episodes_and_ticks(bases, tmp_path) -> None:
    folder = make_idr(
        bases["act"], tmp_path / "idr", "--tau", "3", "--diagnostics-dir", str(tmp_path / "d")
    )
    policy, pre, post = load(folder)
    for _ in range(2):  # two episodes of 9 steps, replanning every 4
        rollout(policy, pre, post, steps=9)
    policy.reset()
    rows = read_sidecar(tmp_path / "d")
    assert sorted(set(rows["episode"])) == [0, 1]
    ep = rows[(rows["episode"] == 1) & (rows["env"] == 0)]
    assert list(ep["tick"]) == [0, 1, 2] and list(ep["step"]) == [1, 5, 9]
    assert (rows["wait_ms"] >= rows["inference_ms"]).all()


def test_training_is_refused_with_one_line(bases, tmp_path) -> None:
    from lerobot_policy_idr.configuration_idr import IDRConfigError

    policy, _, _ = load(make_idr(bases["act"], tmp_path / "idr", "--tau", "3"))
    with pytest.raises(IDRConfigError, match="training-free: train the base policy"):
        policy.forward({})
    with pytest.raises(IDRConfigError, match="training-free"):
        policy.config.get_optimizer_preset()


@pytest.mark.parametrize("kind", ["pi05", "pi0"])
def test_flow_matching_E_equals_the_harness_with_shared_noise(tmp_path, monkeypatch, kind) -> None:
    """pi0 / pi0.5 (shrunk widths, lerobot's classes): one draw of noise for the three thirds;
    the plugin's chunk and E_img equal the harness's for the same noise."""
    from training.toy_checkpoints import (
        build_local_tokenizer,
        build_pi,
        tiny_pi_gemma,
    )
    from workers.backbones.base import Observation

    tiny_pi_gemma(monkeypatch)
    tok = build_local_tokenizer(tmp_path / "tok", ["pick it", "place it"])
    base = build_pi(kind, tmp_path / kind, tok, monkeypatch)
    folder = make_idr(
        base,
        tmp_path / "idr",
        "--tau",
        "1e9",
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    backbone, harness = _harness(base, 1e9)
    assert backbone.crn_mode == "shared_noise"
    policy, pre, post = load(folder)
    g = torch.Generator().manual_seed(0)
    images = {c: torch.rand(2, 3, 32, 32, generator=g) for c in ("agentview", "wrist")}
    state, tasks = torch.rand(2, 8, generator=g), ["pick it", "place it"]
    step = harness.infer(Observation(images, state, tasks), step_seed=3)
    obs = {**{f"observation.images.{c}": v for c, v in images.items()}, "observation.state": state}
    with torch.inference_mode():
        ours = post(
            policy.predict_action_chunk(
                pre({**obs, "task": tasks}), noise=backbone.make_noise(2, 3)
            )
        )
    assert torch.equal(ours, step.action)
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    assert np.array_equal(
        rows["e_img"].to_numpy().astype(np.float32), step.diag.to_numpy()["e_img"]
    )
    assert (rows["e_img"] > 0).all()


def test_xvla_samples_from_its_seed_and_keeps_xvlas_env_processors(tmp_path) -> None:
    """X-VLA (the paper's CALVIN and SIMPLER backbone; tiny Florence-2 built offline) ignores
    a noise input: three forwards under one seed, which reaches its sampler (equal to the
    harness closed loop: ``test_closed_loop.py``). And lerobot picks X-VLA's env processors by
    isinstance on the policy config: an idr config wrapping X-VLA gets them too."""
    from lerobot.envs.configs import LiberoEnv
    from lerobot.envs.factory import make_env_pre_post_processors

    from training.toy_checkpoints import build_local_tokenizer
    from training.toy_xvla_checkpoint import build_xvla

    tok = build_local_tokenizer(tmp_path / "tok", ["pick it", "place it"])
    base = build_xvla(tmp_path / "xvla", tok)
    folder = make_idr(
        base,
        tmp_path / "idr",
        "--tau",
        "1e9",
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    policy, pre, post = load(folder)
    assert policy.crn == "seeded_rng"
    g = torch.Generator().manual_seed(0)
    obs = {
        "observation.images.agentview": torch.rand(2, 3, 64, 64, generator=g),
        "observation.state": torch.rand(2, 8, generator=g),
        "task": ["pick it", "place it"],
    }
    # another seed gives other actions (the seed reaches the sampler), the same seed the same
    with torch.inference_mode():
        ours = post(policy.predict_action_chunk(pre(dict(obs)), seed=5))
        again = post(policy.predict_action_chunk(pre(dict(obs)), seed=5))
        other = post(policy.predict_action_chunk(pre(dict(obs)), seed=6))
    assert torch.equal(again, ours) and not torch.equal(other, ours)
    policy.sidecar.flush()
    assert (read_sidecar(tmp_path / "d")["e_img"] > 0).all()  # the image moves the actions
    env_pre, env_post = make_env_pre_post_processors(
        LiberoEnv(task="libero_spatial"), policy.config
    )
    names = [type(s).__name__ for s in env_pre.steps] + [type(s).__name__ for s in env_post.steps]
    assert (
        "XVLAImageNetNormalizeProcessorStep" in names
        and "XVLARotation6DToAxisAngleProcessorStep" in names
    )
    assert policy.config.type == "idr"
    policy.config._save_pretrained(tmp_path)  # still saves as an idr config
    assert json.loads((tmp_path / "config.json").read_text())["type"] == "idr"


def test_a_three_pass_folder_run_as_temporal_reads_its_factual_rows(bases, tmp_path) -> None:
    """``--policy.path`` of a folder made for E with ``--policy.mode=temporal``: its
    preprocessor still makes the counterfactual rows, the policy averages the factual ones, as
    a folder made for temporal does."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors
    from lerobot_policy_idr.modeling_idr import IDRPolicy

    e_folder = make_idr(bases["act"], tmp_path / "E", "--tau", "3")
    temporal = rollout(*load(make_idr(bases["act"], tmp_path / "T", "--mode", "temporal")), 3)
    cfg = PreTrainedConfig.from_pretrained(e_folder)
    cfg.mode = "temporal"  # --policy.mode=temporal; the processors stay the folder's
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(e_folder))
    assert "IDRCounterfactualBatchStep" in [type(s).__name__ for s in pre.steps]
    overridden = rollout(IDRPolicy.from_pretrained(e_folder, config=cfg), pre, post, 3)
    assert all(torch.equal(a, b) for a, b in zip(temporal, overridden, strict=True))
