from __future__ import annotations

import torch
from idr_core.refiner import RefinerConfig

from workers.backbones.base import Observation
from workers.backbones.noop import NoopBackbone
from workers.policy.wrapper import IDRWrapper


def test_noop_chunk_is_zero_motion_gripper_held_and_has_no_effects() -> None:
    obs = Observation({"cam": torch.rand(2, 3, 8, 8)}, torch.rand(2, 8), ["a", "b"])
    step = IDRWrapper(NoopBackbone(action_dim=7, chunk_len=3), RefinerConfig(mode="E")).infer(obs)
    assert step.action.shape == (2, 3, 7)
    assert torch.equal(step.action[..., :6], torch.zeros(2, 3, 6))
    assert torch.equal(step.action[..., 6], -torch.ones(2, 3))
    assert torch.equal(step.diag.e_img, torch.zeros(2))  # nothing depends on the inputs
