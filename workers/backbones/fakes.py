"""Fake backbones for unit tests and the smoke preset: closed-form, not learned. Named as fakes.

``FakeMarkerBackbone`` reads the red marker's position ``m`` from the image (centroid of the
red pixels, ``m = 0`` for an image without one, e.g. a zeroed image) and the agent position
``p`` from the state, and predicts the same action at each of the chunk's T steps:

    a = gain * (m - p) + noise_std * noise

so the counterfactual deltas of IDR are known in closed form (with shared noise):

    d_img  = a(v, s) - a(0, s) = gain * m        e_img  = gain * ||m|| * sqrt(T)
    d_prop = a(v, s) - a(v, 0) = -gain * p       e_prop = gain * ||p|| * sqrt(T)
"""

from __future__ import annotations

import time
from typing import Any, ClassVar

import numpy as np
import torch

from workers.backbones.base import Observation


def _as_tensor(x: Any) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.from_numpy(np.asarray(x))


def marker_position(images: torch.Tensor) -> torch.Tensor:
    """(B, 3, H, W) in [0, 1] -> (B, 2) plane coordinates of the red marker's centroid (0 if none)."""
    b, _, h, w = images.shape
    red = (images[:, 0] > 0.5) & (images[:, 1] < 0.5)
    rows = torch.arange(h, dtype=torch.float32).view(1, h, 1)
    cols = torch.arange(w, dtype=torch.float32).view(1, 1, w)
    count = red.sum(dim=(1, 2)).clamp(min=1).float()
    r = (red * rows).sum(dim=(1, 2)) / count
    c = (red * cols).sum(dim=(1, 2)) / count
    x = c / (w - 1) * 2 - 1
    y = 1 - r / (h - 1) * 2
    found = red.flatten(1).any(dim=1)
    return torch.where(found[:, None], torch.stack([x, y], dim=1), torch.zeros(b, 2))


class FakeMarkerBackbone:
    """Closed-form policy for FakeMarkerEnv; stochastic when ``noise_std > 0``."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset()

    def __init__(
        self,
        chunk_len: int = 4,
        gain: float = 5.0,
        noise_std: float = 0.0,
        camera: str = "agentview",
        can_batch: bool = True,
        fresh_noise_seed: int = 1234,
        delay_s: float = 0.0,
        busy_s: float = 0.0,
    ) -> None:
        self.name = "fake_marker"
        self.chunk_len = chunk_len
        self.action_dim = 2
        self.gain = gain
        self.noise_std = noise_std
        self.camera = camera
        self.can_batch = can_batch
        self.delay_s = delay_s  # simulated inference time, sleeping (tests of scheduling, faults)
        self.busy_s = busy_s  # simulated inference time, burning CPU (throughput benchmarks)
        # Used when the caller passes no noise: independent draws per call.
        self._fresh = torch.Generator().manual_seed(fresh_noise_seed)

    def reset(self) -> None:
        pass

    def make_noise(self, batch_size: int, seed: int) -> torch.Tensor | None:
        if self.noise_std == 0:
            return None
        gen = torch.Generator().manual_seed(seed)
        return torch.randn(batch_size, self.chunk_len, self.action_dim, generator=gen)

    def predict_chunk(
        self, obs: Observation, noise: Any | None = None, intervention: Any | None = None
    ) -> torch.Tensor:
        if intervention is not None:
            raise ValueError(f"{self.name} applies no interventions itself (raw space only)")
        if self.delay_s:
            time.sleep(self.delay_s)
        if self.busy_s:
            end = time.perf_counter() + self.busy_s
            while time.perf_counter() < end:
                pass
        images = _as_tensor(obs.images[self.camera]).float()
        state = _as_tensor(obs.state).float()
        m = marker_position(images)
        a = (self.gain * (m - state[:, :2]))[:, None, :].expand(-1, self.chunk_len, -1)
        if self.noise_std > 0:
            if noise is None:
                noise = torch.randn(a.shape, generator=self._fresh)
            a = a + self.noise_std * _as_tensor(noise)
        return a.contiguous()
