"""How IDR gives a policy type's three passes the same noise (idr_core.sampling)."""

from __future__ import annotations

from idr_core.sampling import crn_mode


def _takes_noise(batch, noise=None):  # a predict_action_chunk that names noise
    return batch


def _no_noise(batch):
    return batch


def test_sampling_policies_without_usable_noise_run_three_seeded_passes() -> None:
    # VQ-BeT samples its codes (torch.multinomial) and TD-MPC plans with CEM noise: neither is
    # deterministic, so one forward per pass under the same seed
    assert crn_mode("vqbet", _no_noise) == "seeded_rng"
    assert crn_mode("tdmpc", _no_noise) == "seeded_rng"
    # VLA-JEPA and X-VLA name a noise argument and ignore it: sharing a draw would not share it
    assert crn_mode("vla_jepa", _takes_noise) == "seeded_rng"
    assert crn_mode("xvla", _takes_noise) == "seeded_rng"


def test_deterministic_and_noise_taking_types() -> None:
    assert crn_mode("act", _no_noise) == "deterministic"
    assert crn_mode("tiny_vla", _no_noise) == "deterministic"
    assert crn_mode("smolvla", _takes_noise) == "shared_noise"
    assert crn_mode("pi0", _no_noise) == "shared_noise"  # noise through **kwargs
