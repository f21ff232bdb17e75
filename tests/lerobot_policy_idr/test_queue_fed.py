"""Bases whose ``predict_action_chunk`` reads the observation queues their ``select_action``
fills: VQ-BeT (a discretized action head: actions decoded from codes first, refined in action
space after) and Multi-Task DiT (CLIP-conditioned diffusion). IDR keeps queues of its own for
the 3B rows and lends them for each forward (small models, random weights, built offline; VQ-BeT's
residual VQ marked trained, Multi-Task DiT's CLIP a local folder)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from idr_core.sidecar import read_sidecar

from tests.lerobot_policy_idr.conftest import load, make_idr, obs_batch, rollout
from tests.lerobot_policy_idr.test_modeling_idr import _base, _harness
from training.toy_checkpoints import (
    build_multi_task_dit,
    build_tiny_clip,
    build_vqbet,
)

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def vqbet(tmp_path_factory):
    root = tmp_path_factory.mktemp("vqbet")
    clip = build_tiny_clip(root / "tiny-clip", [f"task {i}" for i in range(2)])
    return {
        "sampling": build_vqbet(root / "sampling"),
        "argmax": build_vqbet(root / "argmax", temperature=1e-4),
        "multi_task_dit": build_multi_task_dit(root / "dit", clip),
    }


@pytest.mark.parametrize("kind", ["sampling", "multi_task_dit"])
def test_baseline_is_the_base_bit_for_bit(vqbet, tmp_path, kind) -> None:
    folder = make_idr(
        vqbet[kind], tmp_path / "idr", "--mode", "baseline", "--diagnostics-dir", str(tmp_path)
    )
    torch.manual_seed(0)
    theirs = rollout(*_base(vqbet[kind]), steps=9)
    torch.manual_seed(0)
    ours = rollout(*load(folder), steps=9)
    for t, (a, b) in enumerate(zip(theirs, ours, strict=True)):
        assert torch.equal(a, b), f"step {t}"


def test_diagnose_follows_the_bases_own_rollout_history_included(vqbet, tmp_path) -> None:
    """Two observation steps: the base's select_action queues every step's frame and predicts
    every 4th. IDR's queues must hold the same frames (not only the inference steps'), so its
    base rows give the base's actions: equal up to the float rounding of a 3B batch (codes
    sampled at a temperature near 0, so the draw is the argmax in both)."""
    folder = make_idr(
        vqbet["argmax"], tmp_path / "idr", "--mode", "diagnose", "--diagnostics-dir", str(tmp_path)
    )
    theirs = rollout(*_base(vqbet["argmax"]), steps=12)
    policy, pre, post = load(folder)
    ours = rollout(policy, pre, post, steps=12)
    diff = max(float((a - b).abs().max()) for a, b in zip(theirs, ours, strict=True))
    assert diff < 1e-5, diff
    assert {k: len(q) for k, q in policy.base._queues.items() if k != "action"} == {
        "observation.images": 0,
        "observation.state": 0,
    }  # the base's own queues untouched: IDR lent its own
    # IDR's queues hold the last two steps' frames (11 was no inference step: 0, 4, 8 were)
    last = [q[:2] for q in policy._fed["observation.state"]]
    with torch.inference_mode():
        want = [pre(obs_batch(2, seed=t))["observation.state"][:2] for t in (10, 11)]
    assert all(torch.equal(a, b) for a, b in zip(last, want, strict=True))


@pytest.mark.parametrize("kind", ["sampling", "multi_task_dit"])
def test_mode_E_equals_the_harness_and_the_image_moves_the_decoded_actions(
    vqbet, tmp_path, kind
) -> None:
    """The same checkpoint, observation and seed: the plugin's refined chunk and diagnostics
    equal idr-eval's IDRWrapper around its lerobot backbone (three seeded passes each); the
    decoded counterfactual without the image differs from the factual one."""
    from workers.backbones.base import Observation

    base = vqbet[kind]
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
        policy.reset()  # the first inference of an episode: the frame repeated, both ways
        with torch.inference_mode():
            ours = post(policy.predict_action_chunk(pre(obs), noise=backbone.make_noise(2, seed)))
        assert torch.equal(ours, step.action), f"seed {seed}"
        assert not torch.equal(step.a_base, step.a_no_img)  # decoded actions move without the image
        assert not torch.equal(step.action, step.a_base)  # refined: the comparison is not vacuous
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    diag = step.diag.to_numpy()
    assert (rows["e_img"] > 0).all()
    for key in ("e_img", "e_prop", "r_img", "gate", "w_prop"):
        assert np.array_equal(rows[key].to_numpy()[-2:].astype(np.float32), diag[key]), key


def test_lerobot_eval_runs_it_on_pusht_and_zeroes_its_one_camera(tmp_path) -> None:
    """lerobot-eval's CLI on PushT, whose one camera is lerobot's ``observation.image`` (not
    ``observation.images.<cam>``): IDR zeroes it too, so E_img is measured (it read 0.0 when
    only the plural prefix counted as a camera)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    base = build_vqbet(tmp_path / "base", image=96, state=2, action=2, cams=("image!",))
    folder = make_idr(
        base, tmp_path / "idr", "--tau", "0.05", "--diagnostics-dir", str(tmp_path / "d")
    )
    cmd = [
        str(Path(sys.executable).parent / "lerobot-eval"),
        f"--policy.path={folder}",
        "--env.type=pusht",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        "--env.episode_length=24",
        f"--output_dir={tmp_path / 'out'}",
    ]
    out = subprocess.run(
        cmd, capture_output=True, text=True, env={**os.environ, "HF_HUB_OFFLINE": "1"}, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    rows = read_sidecar(tmp_path / "d")
    assert list(rows["step"]) == [1, 5, 9, 13, 17, 21]  # its chunk of 4, executed whole
    assert (rows["e_img"] > 0).all() and (rows["e_prop"] > 0).all()
