"""``pipeline.api.diagnose`` on the shipped tiny VLA: finite effects, R_img in [0, 1], the
harness's own diagnose values on the same frames, the paper's formula by hand, and a policy
object in memory giving what its checkpoint folder gives."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from pipeline.api import DEFAULT_INTERVENTION, ConfigError, diagnose
from pipeline.api.diagnose import frames_observation

ROOT = Path(__file__).resolve().parents[3]
TINY = ROOT / "checkpoints" / "tiny_vla"
N = 6

pytestmark = pytest.mark.slow  # loads a lerobot policy (lerobot's import: seconds)


@pytest.fixture(scope="module")
def frames() -> dict:
    rng = np.random.default_rng(0)
    return {
        "images": {
            cam: rng.random((N, 3, 96, 96), dtype=np.float32) for cam in ("agentview", "wrist")
        },
        "state": (0.1 * rng.standard_normal((N, 8))).astype(np.float32),
        "instruction": ["pick up the red cube"] * 3 + ["put the blue cube in the bin"] * 3,
    }


@pytest.fixture(scope="module")
def measured(frames: dict):
    return diagnose(TINY, frames)


def test_finite_effects_and_r_img_in_unit_interval(measured) -> None:
    assert measured.n == N and measured.policy == "lerobot:tiny_vla"
    for values in (measured.e_img, measured.e_prop, measured.r_img):
        assert values.shape == (N,) and np.isfinite(values).all()
    assert (measured.e_img > 0).all() and (measured.e_prop > 0).all()
    assert ((measured.r_img >= 0) & (measured.r_img <= 1)).all()
    assert measured.r_img_mean == pytest.approx(measured.r_img.mean())
    assert measured.e_img_mean == pytest.approx(measured.e_img.mean())
    lo, hi = measured.r_img_ci
    assert lo <= measured.r_img_mean <= hi and hi - lo > 0


def test_equal_to_the_harness_diagnose_and_the_formula(frames: dict, measured) -> None:
    from idr_core.refiner import RefinerConfig

    from workers.backbones.lerobot.adapter import LerobotBackbone
    from workers.policy.wrapper import IDRWrapper

    backbone = LerobotBackbone(str(TINY))
    wrapper = IDRWrapper(backbone, RefinerConfig(mode="diagnose"), DEFAULT_INTERVENTION)
    obs = frames_observation(frames)
    diag = wrapper.infer(obs, step_seed=0).diag
    np.testing.assert_array_equal(measured.e_img, diag.e_img.numpy().astype(np.float64))
    np.testing.assert_array_equal(measured.r_img, diag.r_img.numpy().astype(np.float64))
    # by hand: do(V) a black image, do(S) zero after the normalizer, norms over the whole chunk
    no_img, no_prop = wrapper.counterfactuals(obs)
    a = backbone.predict_chunk(obs)
    a_v = backbone.predict_chunk(no_img)
    a_s = backbone.predict_chunk(no_prop, intervention=DEFAULT_INTERVENTION)
    e_img = (a - a_v).flatten(1).norm(dim=1).numpy()
    e_prop = (a - a_s).flatten(1).norm(dim=1).numpy()
    np.testing.assert_allclose(measured.e_img, e_img, rtol=1e-5)
    np.testing.assert_allclose(measured.e_prop, e_prop, rtol=1e-5)
    np.testing.assert_allclose(measured.r_img, e_img / (e_img + e_prop + 1e-6), rtol=1e-5)


def test_batches_and_single_frames_give_the_same_values(frames: dict, measured) -> None:
    singles = [
        {
            "images": {c: x[i] for c, x in frames["images"].items()},
            "state": frames["state"][i],
            "instruction": frames["instruction"][i],
        }
        for i in range(N)
    ]
    again = diagnose(TINY, singles, batch_size=4)  # a deterministic policy: batching is moot
    np.testing.assert_allclose(again.e_img, measured.e_img, rtol=1e-4)
    np.testing.assert_allclose(again.r_img, measured.r_img, rtol=1e-4)


def test_a_policy_in_memory_gives_what_its_folder_gives(frames: dict, measured) -> None:
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class
    from lerobot_policy_idr.processor_idr import load_base_processors

    cfg = PreTrainedConfig.from_pretrained(TINY)
    cfg.pretrained_path = TINY  # as lerobot's make_policy sets it
    policy = get_policy_class(cfg.type).from_pretrained(TINY, config=cfg)
    policy.train()  # as a training loop holds it
    from_memory = diagnose(policy, frames)  # processors from config.pretrained_path
    np.testing.assert_allclose(from_memory.e_img, measured.e_img, rtol=1e-5)
    np.testing.assert_allclose(from_memory.r_img, measured.r_img, rtol=1e-5)
    assert policy.training  # given back in the mode it was in
    pre, post = load_base_processors(TINY, "cpu")
    given = diagnose(policy, frames, preprocessor=pre, postprocessor=post)
    np.testing.assert_allclose(given.e_prop, measured.e_prop, rtol=1e-5)
    assert pre.after_step_hooks == []  # the caller's pipeline keeps no hook of ours
    policy.config.pretrained_path = None
    with pytest.raises(ConfigError, match="pass preprocessor= and postprocessor="):
        diagnose(policy, frames)
    with torch.no_grad():  # a changed weight changes the measure: nothing is cached
        for p in policy.parameters():
            p.mul_(0.5)
    changed = diagnose(policy, frames, preprocessor=pre, postprocessor=post)
    assert not np.allclose(changed.e_img, measured.e_img)


def test_bad_frames_and_folders_are_refused_before_loading(frames: dict, tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="does not exist"):
        diagnose(tmp_path / "nope", frames)
    pixels = {**frames, "images": {c: x * 255 for c, x in frames["images"].items()}}
    with pytest.raises(ConfigError, match=r"floats in \[0, 1\]"):
        diagnose(TINY, pixels)
    with pytest.raises(ConfigError, match=r"missing \['state'\]"):
        diagnose(TINY, {"images": frames["images"], "instruction": "x"})
    short = {**frames, "instruction": ["one"]}
    with pytest.raises(ConfigError, match=r"frames: Observation\.state has batch 6"):
        diagnose(TINY, short)
    with pytest.raises(ConfigError, match="a lerobot checkpoint folder or a lerobot"):
        diagnose(object(), frames)


def test_the_default_intervention_is_the_default_configs() -> None:
    section = yaml.safe_load((ROOT / "conf" / "default.yaml").read_text())["intervention"]
    assert {k: getattr(DEFAULT_INTERVENTION, k) for k in section} == section
