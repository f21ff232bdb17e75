"""The IDR wrapper: one 3B forward with common random numbers, equal to the sequential path."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig, refine

from tests.doubles.backbones import CountingMarkerBackbone
from workers.backbones.base import Observation
from workers.backbones.fakes import FakeMarkerBackbone
from workers.envs.fakes import FakeMarkerEnv
from workers.episode.observation import to_policy_observation
from workers.policy.wrapper import IDRWrapper


def _batch(n: int = 3, seed: int = 0) -> Observation:
    env = FakeMarkerEnv()
    resets = [env.reset("reach", i, seed) for i in range(n)]
    parts = [to_policy_observation(o, o.status.instruction) for o in resets]
    return Observation(
        images={"agentview": torch.cat([p.images["agentview"] for p in parts])},
        state=torch.cat([p.state for p in parts]),
        instruction=[s for p in parts for s in p.instruction],
    )


def test_batched_is_one_call_of_3b_and_equals_sequential() -> None:
    obs = _batch(3)
    bb = CountingMarkerBackbone(noise_std=0.3)
    batched = IDRWrapper(bb, RefinerConfig(tau=100.0), batched=True).infer(obs, step_seed=5)
    assert bb.calls == [9]
    bb.calls.clear()
    sequential = IDRWrapper(bb, RefinerConfig(tau=100.0), batched=False).infer(obs, step_seed=5)
    assert bb.calls == [3, 3, 3]
    assert batched.batched and not sequential.batched and batched.crn
    for name in ("action", "a_base", "a_no_img", "a_no_prop"):
        torch.testing.assert_close(
            getattr(batched, name), getattr(sequential, name), rtol=0, atol=0
        )


def test_fake_backbone_deltas_match_closed_form() -> None:
    obs = _batch(3)
    bb = FakeMarkerBackbone(chunk_len=4, gain=5.0, noise_std=0.2)
    step = IDRWrapper(bb, RefinerConfig(mode="diagnose")).infer(obs, step_seed=1)
    m = np.stack([_marker(obs, i) for i in range(3)])
    p = obs.state.numpy()
    np.testing.assert_allclose(
        step.diag.e_img.numpy(), 5.0 * np.linalg.norm(m, axis=1) * 2, rtol=1e-5
    )
    np.testing.assert_allclose(
        step.diag.e_prop.numpy(), 5.0 * np.linalg.norm(p, axis=1) * 2, rtol=1e-5
    )
    torch.testing.assert_close(step.action, step.a_base)  # diagnose executes a_base


def _marker(obs: Observation, i: int) -> np.ndarray:
    from workers.backbones.fakes import marker_position

    return marker_position(obs.images["agentview"][i : i + 1])[0].numpy()


def test_shared_noise_identical_inputs_gives_exactly_zero_delta() -> None:
    """CRN: with identical inputs and one noise draw, a stochastic head's delta is exactly 0."""
    obs = _batch(2)
    bb = FakeMarkerBackbone(noise_std=1.0)
    noise = bb.make_noise(2, seed=9)
    a1 = bb.predict_chunk(obs, noise=noise)
    a2 = bb.predict_chunk(obs, noise=noise)
    a3 = bb.predict_chunk(obs, noise=noise)
    _, diag = refine(a1, a2, a3, RefinerConfig())
    assert torch.equal(diag.e_img, torch.zeros(2)) and torch.equal(diag.e_prop, torch.zeros(2))
    # with independent noise (none passed: fresh draws per call) the same inputs give delta != 0
    b1, b2, b3 = (bb.predict_chunk(obs) for _ in range(3))
    _, diag = refine(b1, b2, b3, RefinerConfig())
    assert (diag.e_img > 0.1).all() and (diag.e_prop > 0.1).all()


def test_wrapper_passes_the_same_noise_to_all_three_thirds() -> None:
    seen: list[torch.Tensor] = []

    class Spy(FakeMarkerBackbone):
        def predict_chunk(self, obs, noise=None, intervention=None):
            seen.append(noise)
            return super().predict_chunk(obs, noise=noise, intervention=intervention)

    IDRWrapper(Spy(noise_std=1.0), batched=True).infer(_batch(2), step_seed=3)
    (n,) = seen
    assert n.shape[0] == 6
    assert torch.equal(n[:2], n[2:4]) and torch.equal(n[:2], n[4:])
    seen.clear()
    IDRWrapper(Spy(noise_std=1.0), batched=False).infer(_batch(2), step_seed=3)
    assert len(seen) == 3 and all(torch.equal(seen[0], s) for s in seen)


def test_counterfactual_inputs_are_the_interventions() -> None:
    obs = _batch(2)
    pol = IDRWrapper(FakeMarkerBackbone())
    no_img, no_prop = pol.counterfactuals(obs)
    assert float(no_img.images["agentview"].abs().sum()) == 0.0
    torch.testing.assert_close(no_img.state, obs.state)
    assert float(no_prop.state.abs().sum()) == 0.0
    torch.testing.assert_close(no_prop.images["agentview"], obs.images["agentview"])
    # the factual observation is left untouched
    assert float(obs.images["agentview"].sum()) > 0 and float(obs.state.abs().sum()) > 0


def test_baseline_mode_runs_no_counterfactual_pass() -> None:
    bb = CountingMarkerBackbone()
    step = IDRWrapper(bb, RefinerConfig(mode="baseline")).infer(_batch(2))
    assert bb.calls == [2]
    assert step.diag is None and step.a_no_img is None
    torch.testing.assert_close(step.action, step.a_base)


def test_each_inference_runs_its_own_cell_on_one_wrapper() -> None:
    """One wrapper serves every cell of a run: the settings travel with each inference, and
    one inference's settings leave the next one's untouched."""
    pol = IDRWrapper(FakeMarkerBackbone(), RefinerConfig(mode="baseline"))
    e = pol.infer(_batch(1), 0, RefinerConfig(mode="E", tau=1e9))
    assert e.diag is not None and not torch.equal(e.action, e.a_base)
    after = pol.infer(_batch(1), 0)  # the wrapper's own default: baseline, unchanged
    assert after.diag is None and torch.equal(after.action, after.a_base)
    assert not hasattr(pol, "set_config")


def test_normalized_space_refused_for_raw_only_backbone() -> None:
    with pytest.raises(
        ValueError,
        match=r"intervention.state_space='normalized' is not supported by backbone 'fake_marker'",
    ):
        IDRWrapper(FakeMarkerBackbone(), intervention=InterventionConfig(state_space="normalized"))


def test_batched_refused_when_backbone_cannot_batch() -> None:
    with pytest.raises(ValueError, match="cannot batch"):
        IDRWrapper(FakeMarkerBackbone(can_batch=False), batched=True)
    assert IDRWrapper(FakeMarkerBackbone(can_batch=False)).batched is False
