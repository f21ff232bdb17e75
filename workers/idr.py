"""The IDR refiner as the harness imports it.

The implementation lives in the ``lerobot_policy_idr`` distribution (``idr_core.refiner``),
the same code that the lerobot policy type ``idr`` runs on a robot; this module keeps the
harness's contract: ``workers.idr.refine(a_base, a_no_img, a_no_prop, RefinerConfig(...))``.
The refiner's settings are ``RefinerConfig`` everywhere in the harness; ``IDRConfig`` is the
lerobot policy config of type ``idr`` (``lerobot_policy_idr.configuration_idr``). The old name
``workers.idr.IDRConfig`` still imports, with a FutureWarning.
"""

from __future__ import annotations

import warnings
from typing import Any

from idr_core.refiner import (
    GUIDANCES,
    MODE_DESCRIPTIONS,
    MODES,
    Diagnostics,
    Guidance,
    Mode,
    RefinerConfig,
    refine,
)

__all__ = [
    "GUIDANCES",
    "MODES",
    "MODE_DESCRIPTIONS",
    "Diagnostics",
    "Guidance",
    "Mode",
    "RefinerConfig",
    "refine",
]


def __getattr__(name: str) -> Any:
    if name == "IDRConfig":
        warnings.warn(
            "workers.idr.IDRConfig is now workers.idr.RefinerConfig (IDRConfig is the lerobot "
            "policy config of type idr, in lerobot_policy_idr.configuration_idr)",
            FutureWarning,
            stacklevel=2,
        )
        return RefinerConfig
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
