"""Fault-injecting backbone doubles: the fake marker backbone with faults placed by call."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import torch

from tests.doubles import faults
from workers.backbones.base import Observation
from workers.backbones.fakes import FakeMarkerBackbone


class CountingMarkerBackbone(FakeMarkerBackbone):
    """FakeMarkerBackbone that records the batch size of every ``predict_chunk`` call (how many
    forwards, of how many rows), cleared by ``reset``."""

    def __init__(self, **params: Any) -> None:
        super().__init__(**params)
        self.calls: list[int] = []

    def reset(self) -> None:
        super().reset()
        self.calls.clear()

    def predict_chunk(
        self, obs: Observation, noise: Any | None = None, intervention: Any | None = None
    ) -> torch.Tensor:
        self.calls.append(obs.batch_size)
        return super().predict_chunk(obs, noise, intervention)


class FaultyMarkerBackbone(FakeMarkerBackbone):
    """FakeMarkerBackbone whose calls fail on purpose, by call number (0-based, counted over
    this object's life, not cleared by reset): ``nonfinite_calls`` return ``nonfinite_value``
    (NaN or inf) in every action; calls from ``hang_from_call`` on never return;
    ``exit_on_call`` kills the process at that call (a policy actor that crashes), once per test
    with ``once_dir``."""

    def __init__(
        self,
        nonfinite_calls: tuple[int, ...] = (),
        nonfinite_value: float = float("nan"),
        hang_from_call: int | None = None,
        exit_on_call: int | None = None,
        once_dir: str | None = None,
        **params: Any,
    ) -> None:
        super().__init__(**params)
        self.nonfinite_calls = frozenset(nonfinite_calls)
        self.nonfinite_value = float(nonfinite_value)
        self.hang_from_call = hang_from_call
        self.exit_on_call, self.once_dir = exit_on_call, once_dir
        self._n_calls = 0

    def predict_chunk(
        self, obs: Observation, noise: Any | None = None, intervention: Any | None = None
    ) -> torch.Tensor:
        call, self._n_calls = self._n_calls, self._n_calls + 1
        if self.hang_from_call is not None and call >= self.hang_from_call:
            faults.hang_forever()
        if call == self.exit_on_call and faults.should_fire(
            "backbone_exit", call, {call}, self.once_dir
        ):
            import os

            os._exit(9)
        a = super().predict_chunk(obs, noise, intervention)
        if call in self.nonfinite_calls:
            a = torch.full_like(a, self.nonfinite_value)
        return a


class GatedMarkerBackbone(FakeMarkerBackbone):
    """FakeMarkerBackbone whose calls wait until the file ``gate`` exists: a test holds a run
    in flight for as long as it needs, then lets it finish."""

    def __init__(self, gate: str, **params: Any) -> None:
        super().__init__(**params)
        self.gate = Path(gate)

    def predict_chunk(
        self, obs: Observation, noise: Any | None = None, intervention: Any | None = None
    ) -> torch.Tensor:
        while not self.gate.exists():
            time.sleep(0.02)
        return super().predict_chunk(obs, noise, intervention)


class CheckpointedMarkerBackbone(FakeMarkerBackbone):
    """FakeMarkerBackbone that names a checkpoint folder (``path``) as a real backbone does,
    without reading it: for what a run records and checks of the checkpoint."""

    def __init__(self, path: str, **params: Any) -> None:
        super().__init__(**params)
        self.path = path


class SmallDeviceMarkerBackbone(FakeMarkerBackbone):
    """FakeMarkerBackbone on a device that holds at most ``max_rows`` rows per forward: a larger
    forward raises torch's out-of-memory error, as CUDA's allocator would. Every request whose
    instruction names ``always_oom`` fails alone too (a request that cannot fit at all)."""

    def __init__(self, max_rows: int, always_oom: str | None = None, **params: Any) -> None:
        super().__init__(**params)
        self.max_rows = int(max_rows)
        self.always_oom = always_oom
        self.oom_raised = 0

    def predict_chunk(
        self, obs: Observation, noise: Any | None = None, intervention: Any | None = None
    ) -> torch.Tensor:
        too_big = obs.batch_size > self.max_rows
        if too_big or (self.always_oom and any(self.always_oom in s for s in obs.instruction)):
            self.oom_raised += 1
            raise torch.OutOfMemoryError(
                f"CUDA out of memory. Tried to allocate {obs.batch_size} rows (FAKE device of "
                f"{self.max_rows} rows)"
            )
        return super().predict_chunk(obs, noise, intervention)
