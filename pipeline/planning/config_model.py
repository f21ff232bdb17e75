"""The base of every config model: unknown keys refused, frozen, no inf/nan numbers."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StrictModel(BaseModel):
    # inf / nan in a typed number (gpus_per_worker=.inf) is always a mistake
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
