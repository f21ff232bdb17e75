"""VLM policies under IDR: EO1 (Qwen2.5-VL), EVO1 (InternVL3) and VLA-JEPA (Qwen3-VL), each
with a flow-matching or diffusion action head (toy VLM folders and policies with random weights,
built offline). They sample their noise from torch's RNG and take no noise argument (VLA-JEPA
names one and ignores it), so IDR runs three forwards under one seed."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from idr_core.sidecar import read_sidecar

from tests.lerobot_policy_idr.conftest import load, make_idr, obs_batch, rollout, seeded_chunks
from tests.lerobot_policy_idr.test_modeling_idr import _base, _harness
from tests.workers.backbones.vla_jepa_fixtures import build_qwen3vl_folder, build_vla_jepa
from tests.workers.backbones.vlm_fixtures import (
    build_eo1,
    build_evo1,
    build_internvl3_folder,
    build_qwen25vl_folder,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def vlms(tmp_path_factory):
    root = tmp_path_factory.mktemp("vlms")
    return {
        "eo1": build_eo1(root / "eo1", build_qwen25vl_folder(root / "toy-qwen2.5-vl")),
        "evo1": build_evo1(root / "evo1", build_internvl3_folder(root / "toy-internvl3")),
        "vla_jepa": build_vla_jepa(root / "vla_jepa", build_qwen3vl_folder(root / "toy-qwen3-vl")),
    }


@pytest.mark.parametrize("kind", ["eo1", "evo1", "vla_jepa"])
def test_baseline_is_the_base_bit_for_bit(vlms, tmp_path, kind) -> None:
    ckpt = vlms[kind]
    folder = make_idr(
        ckpt, tmp_path / "idr", "--mode", "baseline", "--diagnostics-dir", str(tmp_path)
    )
    base, idr = _base(ckpt), load(folder)  # both loaded before the seed: loading draws from it
    torch.manual_seed(0)
    theirs = rollout(*base, steps=6)
    torch.manual_seed(0)
    ours = rollout(*idr, steps=6)
    for t, (a, b) in enumerate(zip(theirs, ours, strict=True)):
        assert torch.equal(a, b), f"step {t}"


@pytest.mark.parametrize("kind", ["eo1", "evo1", "vla_jepa"])
def test_mode_E_equals_the_harness_and_the_image_moves_the_actions(vlms, tmp_path, kind) -> None:
    """The same checkpoint, observation and seed: the plugin's refined chunk and diagnostics
    equal idr-eval's IDRWrapper around its lerobot backbone; the same seed gives the same chunk,
    another seed another one."""
    from workers.backbones.base import Observation

    base = vlms[kind]
    folder = make_idr(
        base,
        tmp_path / "idr",
        "--tau",
        "1e9",
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    backbone, harness = _harness(base, 1e9)
    assert backbone.crn_mode == "seeded_rng" and backbone.chunk_len == 4
    policy, pre, post = load(folder)
    assert policy.crn == "seeded_rng"
    for seed in range(2):
        obs = obs_batch(2, seed=seed)
        step = harness.infer(
            Observation(
                {"agentview": obs["observation.images.agentview"]},
                obs["observation.state"],
                obs["task"],
            ),
            step_seed=seed,
        )
        with torch.inference_mode():
            ours = post(policy.predict_action_chunk(pre(obs), noise=backbone.make_noise(2, seed)))
            again = post(policy.predict_action_chunk(pre(obs), noise=backbone.make_noise(2, seed)))
            other = post(policy.predict_action_chunk(pre(obs), noise=backbone.make_noise(2, 99)))
        assert torch.equal(ours, step.action), f"seed {seed}"
        assert torch.equal(again, ours) and not torch.equal(other, ours)
        assert not torch.equal(step.a_base, step.a_no_img)  # the image moves the actions
        assert not torch.equal(step.action, step.a_base)  # refined: not a vacuous comparison
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    diag = step.diag.to_numpy()
    assert (rows["e_img"] > 0).all()
    # EVO1 pads its actions to max_action_dim (24) and its postprocessor crops them to 7: the
    # plugin takes the norms over the padded chunk (the padding equal in the three passes),
    # idr-eval over the cropped one, so they may differ in the last bit of float32
    tol = 0 if kind == "eo1" else 1e-6
    for key in ("e_img", "e_prop", "r_img", "gate", "w_prop"):
        got = rows[key].to_numpy()[-6:-4].astype(np.float32)
        np.testing.assert_allclose(got, diag[key], rtol=tol, atol=0, err_msg=key)


@pytest.mark.parametrize("kind", ["eo1", "evo1", "vla_jepa"])
def test_diagnose_executes_the_bases_own_chunk(vlms, tmp_path, kind) -> None:
    """Three forwards of B rows under one seed: the factual third is the base's own forward
    under that seed, so diagnose executes the base's chunk exactly (not even a 3B batch's
    rounding), and the counterfactual thirds move the actions (E_img, E_prop > 0)."""
    ckpt = vlms[kind]
    folder = make_idr(
        ckpt, tmp_path / "idr", "--mode", "diagnose", "--diagnostics-dir", str(tmp_path)
    )
    idr = load(folder)
    chunks = seeded_chunks(idr, _base(ckpt), obs_batch(2, seed=0))
    assert all(torch.equal(ours, theirs) for ours, theirs in chunks)
    assert not torch.equal(chunks[0][0], chunks[1][0])  # the base does sample
    idr[0].sidecar.flush()
    rows = read_sidecar(tmp_path)
    assert len(rows) == 2 * 2 and (rows["e_img"] > 0).all() and (rows["e_prop"] > 0).all()


@pytest.fixture(scope="module")
def libero_vlms(tmp_path_factory):
    """The same policies with lerobot's LIBERO cameras (image, image2)."""
    root = tmp_path_factory.mktemp("libero_vlms")
    cams = ("image", "image2")
    return {
        "eo1": build_eo1(root / "eo1", build_qwen25vl_folder(root / "qwen25"), cams=cams),
        "evo1": build_evo1(root / "evo1", build_internvl3_folder(root / "internvl3"), cams=cams),
        "vla_jepa": build_vla_jepa(root / "jepa", build_qwen3vl_folder(root / "qwen3"), cams=cams),
    }


@pytest.mark.sim
@pytest.mark.parametrize("kind", ["eo1", "evo1", "vla_jepa"])
def test_lerobot_eval_runs_it_on_libero(libero_vlms, tmp_path, kind) -> None:
    """lerobot-eval's own code path (make_env, make_policy, its processors, eval_policy_all) on
    LIBERO with the IDR folder, mode E with the gate on: every executed action is finite and
    in the env's action space, one sidecar row per inference, the image moved every one."""
    from tests.support.lerobot_eval import lerobot_eval_libero
    from workers.envs.suites.libero.assets import ensure_config_env
    from workers.rendering import configure_rendering

    ensure_config_env()
    configure_rendering()
    folder = make_idr(
        libero_vlms[kind], tmp_path / "idr", "--tau", "1e9", "--diagnostics-dir", str(tmp_path)
    )
    steps = 8
    recorded, _ = lerobot_eval_libero(folder, steps=steps, episodes=1, seed=0, size=64)
    actions = np.stack(recorded[0]["actions"])
    assert actions.shape[0] == steps and np.isfinite(actions).all()
    rows = read_sidecar(tmp_path)
    assert len(rows) == steps // 4  # chunks of 4, all executed
    assert (rows["gate"] == 1.0).all() and (rows["e_img"] > 0).all()
    if kind == "vla_jepa":  # its gripper binarized after IDR refined: the env got -1 or 1
        assert set(np.unique(actions[..., 6]).tolist()) <= {-1.0, 1.0}
