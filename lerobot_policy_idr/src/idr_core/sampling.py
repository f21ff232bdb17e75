"""How a lerobot policy type samples, and so how IDR gives its three passes the same noise.

- ``shared_noise``: ``predict_action_chunk`` takes a ``noise`` tensor (pi0 and pi0.5 through
  ``**kwargs`` to ``sample_actions``; SmolVLA and Diffusion by name): one batched forward with
  the draw repeated for the three thirds. Diffusion shares it exactly only under DDIM (DDPM
  draws fresh noise at every denoising step).
- ``seeded_rng``: the policy samples but ignores a noise argument (X-VLA, VLA-JEPA) or has none
  (VQ-BeT draws its codes with ``torch.multinomial``; TD-MPC plans with CEM noise): three
  forwards, each under a forked RNG seeded identically.
- ``deterministic``: no sampling at inference (ACT, the tiny VLA).
"""

from __future__ import annotations

import inspect
from typing import Any

DETERMINISTIC_TYPES = frozenset({"act", "tiny_vla"})
# pi0 / pi0.5 take ``noise`` through ``**kwargs``: the signature alone does not show it.
NOISE_VIA_KWARGS_TYPES = frozenset({"pi0", "pi05"})
# name a ``noise`` argument and ignore it (measured: zeros and ones give the same actions)
NOISE_IGNORED_TYPES = frozenset({"xvla", "vla_jepa"})


def crn_mode(policy_type: str, predict_action_chunk: Any) -> str:
    """``deterministic``, ``shared_noise`` or ``seeded_rng`` for a policy of ``policy_type``
    whose bound ``predict_action_chunk`` is given."""
    if policy_type in DETERMINISTIC_TYPES:
        return "deterministic"
    takes_noise = policy_type not in NOISE_IGNORED_TYPES and (
        policy_type in NOISE_VIA_KWARGS_TYPES
        or "noise" in inspect.signature(predict_action_chunk).parameters
    )
    return "shared_noise" if takes_noise else "seeded_rng"


def noise_shape(config: Any, batch_size: int, action_dim: int) -> tuple[int, ...] | None:
    """The shape of the noise ``predict_action_chunk`` takes for ``batch_size`` rows, for a
    ``shared_noise`` policy's config; None where it has no noise input."""
    if hasattr(config, "max_action_dim"):  # pi0, pi0.5, smolvla: padded to max_action_dim
        return (batch_size, config.chunk_size, config.max_action_dim)
    if getattr(config, "type", None) == "diffusion":
        return (batch_size, config.horizon, action_dim)
    return None
