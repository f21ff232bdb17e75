"""``idr:``: the settings every cell of a run shares, typed at parse time.

A grid axis overrides any of them per cell (``pipeline.planning.grid``), so each field is
optional: absent (or null) means the refiner's own default (``idr_core.refiner.RefinerConfig``,
the paper's values), and what a config gives is kept apart from those defaults, because a
method refuses a setting given for it that it does not read (``idr_core.methods``). The fields
are RefinerConfig's, one for one (a test holds them equal); the ranges are RefinerConfig's
own checks, run once here on the given values so a bad one is refused before any cell is built.
"""

from __future__ import annotations

import dataclasses
from typing import Annotated, Any, Literal

from idr_core.calibration import parse_tau
from idr_core.refiner import GUIDANCES, MODES, RefinerConfig
from pydantic import Field, field_validator, model_validator

from pipeline.planning.config_model import StrictModel
from pipeline.planning.grid import INTERVENTION_KEYS

Mode = Literal[MODES]  # type: ignore[valid-type]
Guidance = Literal[GUIDANCES]  # type: ignore[valid-type]
#: tau: a number (``.inf`` or 999: the gate always open) or a calibrated form (``calibrated``,
#: ``calibrated*K``, ``calibrated_qP``), resolved per suite after the diagnose cell ran
Tau = Annotated[float, Field(allow_inf_nan=True)] | str


class RefinerSettings(StrictModel):
    """The refiner's settings shared by all cells (each None: RefinerConfig's default)."""

    mode: Mode | None = Field(default=None, description="a grid axis, usually")
    alpha: float | None = Field(default=None, description="main (visual) correction")
    beta: float | None = Field(default=None, description="proprioceptive stabilizer")
    lam: float | None = Field(default=None, description="clip bound of the stabilizer")
    tau: Tau | None = Field(
        default=None,
        description="gate threshold: a number (.inf: always on) or calibrated[*K][_qP]",
    )
    eps: float | None = Field(default=None, description="keeps ratios finite")
    guidance: Guidance | None = Field(default=None, description="which effect drives E")
    w: float | None = Field(default=None, description="guidance weight of cfg and pcd")
    samples: int | None = Field(default=None, description="chunks averaged by ensemble")
    te_coeff: float | None = Field(default=None, description="temporal ensembling coefficient")
    horizon: int | None = Field(
        default=None, description="actions executed per inference (None: the run's)"
    )
    clip_actions: bool | None = Field(
        default=None, description="clip refined actions into the base's action bounds"
    )

    @model_validator(mode="before")
    @classmethod
    def _not_an_intervention_key(cls, data: Any) -> Any:
        """An intervention setting written under ``idr:`` is told where it goes (any other
        unknown key is refused as every section's are: ``idr.KEY: unknown key``, with the
        closest name)."""
        if isinstance(data, dict):
            for key in data:
                if key in INTERVENTION_KEYS:
                    raise ValueError(
                        f"{key!r} is an intervention setting, not a refiner one: write it under "
                        f"intervention: {{{key}: {data[key]!r}}} (or as a grid axis, e.g. "
                        f"grid=[{{mode: [diagnose, E]}}, {{{key}: [...]}}])"
                    )
        return data

    @field_validator("tau")
    @classmethod
    def _tau_form(cls, v: float | str | None) -> float | str | None:
        if isinstance(v, str):
            parse_tau(v)  # a clear error for a misspelt calibrated form
        elif v is not None and v != v:
            raise ValueError("tau must be a number >= 0 (.inf: always on) or calibrated[...]")
        return v

    @model_validator(mode="after")
    def _refiner_accepts(self) -> RefinerSettings:
        given = self.given()
        if isinstance(given.get("tau"), str):
            given["tau"] = 0.0  # a calibrated form: its value comes later
        try:
            RefinerConfig(**given)
        except ValueError as e:
            raise ValueError(str(e).replace("RefinerConfig.", "")) from None
        return self

    def given(self) -> dict[str, Any]:
        """The settings the config gives (the rest are RefinerConfig's defaults)."""
        return {k: v for k, v in self.model_dump().items() if v is not None}


def refiner_fields() -> tuple[str, ...]:
    """RefinerConfig's field names, which ``RefinerSettings`` mirrors."""
    return tuple(f.name for f in dataclasses.fields(RefinerConfig))
