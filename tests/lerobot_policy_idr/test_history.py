"""A history-fed base (Diffusion with two observation steps) through the idr policy, as
lerobot-eval calls select_action at every step, and through idr-eval's harness, whose episode
loop sends the past frames with each request: the same frames, so the same actions and
diagnostics, bit for bit, over closed-loop-length sequences."""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest
import torch
from idr_core.sidecar import read_sidecar

from tests.lerobot_policy_idr.conftest import load, make_idr, obs_batch
from tests.lerobot_policy_idr.test_modeling_idr import _harness
from training.toy_checkpoints import build_diffusion

pytestmark = pytest.mark.slow
STEPS = 24  # 6 inferences of 4 executed actions
HORIZON = 4  # the base's n_action_steps, executed by both


def _observation(obs: dict, extras: dict | None = None):
    from workers.backbones.base import Observation

    images = {"agentview": obs["observation.images.agentview"]}
    return Observation(images, obs["observation.state"], obs["task"], extras=extras or {})


@pytest.mark.parametrize("mode", ["diagnose", "E"])
def test_diffusion_with_two_observation_steps_is_the_same_in_harness_and_plugin(
    tmp_path, mode
) -> None:
    from workers.episode.worker import past_frames

    base = build_diffusion(tmp_path / "diffusion", n_obs_steps=2)
    folder = make_idr(
        base, tmp_path / "idr", "--tau", "1e9", "--mode", mode,
        "--diagnostics-dir", str(tmp_path / "d"),
    )  # fmt: skip
    policy, pre, post = load(folder)
    backbone, harness = _harness(base, 1e9, mode)
    frames: deque = deque(maxlen=backbone.history_steps)
    assert backbone.history_steps == 2
    policy.reset()
    ours, theirs, alone, diags = [], [], [], []
    for t in range(STEPS):
        obs = obs_batch(2, seed=t)
        frames.append(_observation(obs))
        noise = None
        if t % HORIZON == 0:  # an inference: the harness's request carries the past frame
            noise = backbone.make_noise(2, t)
            request = _observation(obs, past_frames(list(frames)[:-1]))
            step = harness.infer(request, step_seed=t)
            chunk = step.action
            diags.append(step.diag.to_numpy())
            alone.append(harness.infer(_observation(obs), step_seed=t).action)
        ours.append(chunk[:, t % HORIZON])
        with torch.inference_mode():  # lerobot-eval's call: one action per step
            theirs.append(post(policy.select_action(pre(obs), noise=noise)))
    for t, (a, b) in enumerate(zip(ours, theirs, strict=True)):
        assert torch.equal(a, b), f"step {t}"
    # not vacuous: without its past frame an inference after the first differs
    assert torch.equal(alone[0][:, 0], ours[0])  # the first has no past frame to miss
    assert any(not torch.equal(alone[i][:, 0], ours[HORIZON * i]) for i in range(1, len(alone)))
    policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    for key in ("e_img", "e_prop", "r_img"):
        got = rows[key].to_numpy().reshape(-1, 2).astype(np.float32)
        np.testing.assert_array_equal(got, np.stack([d[key] for d in diags]), err_msg=key)
