"""A backbone that does nothing: zero motion, gripper held. For env smoke runs (LIBERO)."""

from __future__ import annotations

from typing import Any, ClassVar

import torch

from workers.backbones.base import Observation


class NoopBackbone:
    """Predicts a constant chunk: zeros, except the gripper dimension (``gripper_value``)."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset()
    can_batch = True

    def __init__(
        self, action_dim: int = 7, chunk_len: int = 8, gripper_value: float = -1.0
    ) -> None:
        if action_dim < 1 or chunk_len < 1:
            raise ValueError("NoopBackbone: action_dim and chunk_len must be >= 1")
        self.name = "noop"
        self.action_dim = action_dim
        self.chunk_len = chunk_len
        self.gripper_value = gripper_value

    def reset(self) -> None:
        pass

    def make_noise(self, batch_size: int, seed: int) -> None:
        return None

    def predict_chunk(
        self, obs: Observation, noise: Any = None, intervention: Any = None
    ) -> torch.Tensor:
        a = torch.zeros(obs.batch_size, self.chunk_len, self.action_dim)
        a[..., -1] = self.gripper_value
        return a
