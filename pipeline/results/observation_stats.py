"""The estimators of the paper's observations (``pipeline.reporting.observations``), also the
zoo's cards and the open-loop reliance use: R_img as a ratio of mean effects, its 95% interval
from resampling whole episodes, a diagnose cell's pooled effects without the image-zeroed control,
and Spearman's rank correlation with an exact permutation p."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from pipeline.results import aggregate as agg

EPS = agg.RIMG_EPS
N_BOOT = 2000
BINS = 10  # R_img over normalized task progress: bins of equal width
FIFTHS = 5  # the open-loop reliance's progress labels (pipeline.api.frames.FIFTHS)
CONTROL = "@image_blackout"  # the image-zeroed control's perturbation


def ratio(e_img: np.ndarray, e_prop: np.ndarray) -> float:
    return float(e_img.mean() / (e_img.mean() + e_prop.mean() + EPS)) if len(e_img) else math.nan


def rimg_interval(
    steps: pd.DataFrame, n_boot: int = N_BOOT, seed: int = 0
) -> tuple[float, float, float]:
    """R_img of ``steps`` (e_img, e_prop, task_id, episode_index) with a 95% percentile interval
    from resampling whole episodes (steps of one episode are not independent)."""
    per_ep = steps.groupby(["task_id", "episode_index"])[["e_img", "e_prop"]].agg(["sum", "count"])
    s_img = per_ep[("e_img", "sum")].to_numpy()
    s_prop = per_ep[("e_prop", "sum")].to_numpy()
    if len(s_img) == 0:
        return math.nan, math.nan, math.nan
    point = float(s_img.sum() / (s_img.sum() + s_prop.sum() + EPS))
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, len(s_img), size=(n_boot, len(s_img)))
    a, b = s_img[idx].sum(axis=1), s_prop[idx].sum(axis=1)
    boots = a / (a + b + EPS)
    return point, float(np.quantile(boots, 0.025)), float(np.quantile(boots, 0.975))


def without_control(steps: pd.DataFrame) -> pd.DataFrame:
    """``steps`` without the image-zeroed control's (black images at every step: E_img is ~0 by
    construction), which shows in the heatmap, not in a pooled R_img."""
    return steps[~steps["task_id"].astype(str).str.contains(CONTROL, regex=False)]


def pooled_effects(steps: pd.DataFrame) -> dict:
    """R_img of ``steps`` (one diagnose cell's inferences) with its 95% interval, and the mean
    E_img and E_prop: the one estimator of a cell's R_img in the study and the zoo's cards."""
    point, lo, hi = rimg_interval(steps)
    return {
        "r_img": point,
        "r_img_ci95": [lo, hi],
        "e_img": float(steps["e_img"].mean()),
        "e_prop": float(steps["e_prop"].mean()),
        "inferences": len(steps),
    }


def rank_correlation(x: list[float], y: list[float]) -> dict[str, float | int | str]:
    """Spearman's rho of (x, y) and its two-sided permutation p (exact up to 8 points)."""
    from scipy import stats

    n = len(x)
    if n < 3:
        return {"n": n, "rho": math.nan, "p": math.nan, "finding": "too few runs (< 3)"}

    ry = stats.rankdata(y)
    ry = ry - ry.mean()

    def rho_of(rx: np.ndarray, axis: int) -> np.ndarray:
        rx = rx - rx.mean(axis=axis, keepdims=True)
        return (rx * ry).sum(axis=axis) / np.sqrt((rx * rx).sum(axis=axis) * (ry * ry).sum())

    # Spearman's rho is Pearson's r of the (average) ranks; re-pairing the points permutes x's
    # ranks against y's, so only x is permuted (n! pairings, not n!^2) and the statistic is
    # vectorized over them: the exact test of 8 points (40,320 pairings) takes well under a
    # second, where spearmanr called once per pairing took 27 ms each (about 18 minutes; both
    # on a 2-core Intel Xeon)
    res = stats.permutation_test(
        (stats.rankdata(x),),
        rho_of,
        permutation_type="pairings",
        vectorized=True,
        n_resamples=np.inf if n <= 8 else 20000,
        alternative="two-sided",
        random_state=0,
    )
    rho, p = float(res.statistic), float(res.pvalue)
    finding = "inconclusive" if not p < 0.05 else ("positive" if rho > 0 else "negative")
    return {"n": n, "rho": rho, "p": p, "finding": finding}
