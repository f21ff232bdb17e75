"""τ, the gate's threshold, from diagnosed effects: the one statistic the harness (per
backbone x suite, from a diagnose cell) and the lerobot policy's ``lerobot-idr-calibrate``
(from diagnose rollouts' sidecars) both compute.

The paper's rule is the mean E_img of the baseline; the calibrated forms scale it or take a
percentile instead. Which episodes' effects enter is the caller's choice (the harness's is in
``pipeline.results.calibration``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

import numpy as np

CALIBRATED = "calibrated"
_TAU_RE = re.compile(
    r"^calibrated(?:_q(?P<q>\d+(?:\.\d*)?|\.\d+))?(?:\*(?P<k>\d+(?:\.\d*)?(?:e-?\d+)?|\.\d+))?$"
)
TAU_SYNTAX = (
    "write a number (999 or .inf: always on), 'calibrated' (the diagnose cell's mean E_img, "
    "the paper's rule), 'calibrated*K' (K times that mean, K > 0) or 'calibrated_qP' (the P-th "
    "percentile of E_img over the diagnose cell's inferences, 0 < P < 100), or both "
    "('calibrated_q90*0.5'); e.g. tau: calibrated*2"
)


@dataclass(frozen=True)
class TauSpec:
    """A tau computed from the diagnose cell, per backbone x suite, once it has run.

    The statistic is taken over the diagnose cell's inferences of the guided effect: E_img for
    ``guidance: visual``, E_prop for ``proprio`` (the gate thresholds the guided effect)."""

    quantile: float | None = None  # percentile in (0, 100); None: the mean (the paper's rule)
    scale: float = 1.0  # tau = scale * statistic

    @property
    def text(self) -> str:
        """The config spelling, e.g. ``calibrated_q90*0.5``."""
        q = f"_q{self.quantile:g}" if self.quantile is not None else ""
        k = f"*{self.scale:g}" if self.scale != 1.0 else ""
        return f"{CALIBRATED}{q}{k}"

    @property
    def short(self) -> str:
        """For cell ids (file-name safe): ``cal``, ``calx2``, ``calq90``, ``calq90x0.5``."""
        q = f"q{self.quantile:g}" if self.quantile is not None else ""
        k = f"x{self.scale:g}" if self.scale != 1.0 else ""
        return f"cal{q}{k}"

    def resolve(self, effects: Any) -> float:
        """tau from the diagnosed effects (one value per inference)."""
        values = np.asarray(effects, dtype=float)
        values = values[np.isfinite(values)]
        if values.size == 0:
            return math.nan
        stat = values.mean() if self.quantile is None else np.percentile(values, self.quantile)
        return float(self.scale * stat)


def parse_tau(value: Any) -> float | TauSpec:
    """A number, or a :class:`TauSpec` for the calibrated forms; ValueError naming the syntax."""
    if isinstance(value, TauSpec):
        return value
    if isinstance(value, bool):
        raise ValueError(f"tau={value!r} is not a number or a calibrated form; {TAU_SYNTAX}")
    if isinstance(value, int | float):
        return value
    if isinstance(value, str):
        m = _TAU_RE.match(value.strip())
        if m:
            q = float(m["q"]) if m["q"] is not None else None
            k = float(m["k"]) if m["k"] is not None else 1.0
            if q is not None and not 0 < q < 100:
                raise ValueError(f"tau={value!r}: the percentile must be in (0, 100); {TAU_SYNTAX}")
            if not (0 < k < math.inf):
                raise ValueError(f"tau={value!r}: the multiple must be > 0; {TAU_SYNTAX}")
            return TauSpec(q, k)
    raise ValueError(f"tau={value!r} is not a number or a calibrated form; {TAU_SYNTAX}")
