"""The IDR refiner as the harness imports it.

The implementation lives in the ``lerobot_policy_idr`` package (``idr_core.refiner``),
the same code that the lerobot policy type ``idr`` runs on a robot; this module keeps the
harness's contract: ``workers.idr.refine(a_base, a_no_img, a_no_prop, IDRConfig(...))``.
``IDRConfig`` here is the refiner's settings (``lerobot_policy_idr.RefinerConfig``), not the
lerobot policy config of the same name in the package.
"""

from idr_core.refiner import (
    GUIDANCES,
    MODE_DESCRIPTIONS,
    MODES,
    Diagnostics,
    Guidance,
    Mode,
    refine,
)
from idr_core.refiner import RefinerConfig as IDRConfig

__all__ = [
    "GUIDANCES",
    "MODES",
    "MODE_DESCRIPTIONS",
    "Diagnostics",
    "Guidance",
    "IDRConfig",
    "Mode",
    "refine",
]
