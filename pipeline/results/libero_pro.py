"""LIBERO-PRO's tables from the episodes: success per original suite x perturbation family with
the original as the paired reference, per family and overall, and R_img per suite x family.

A perturbed task ``libero_spatial_swap/3`` pairs with ``libero_spatial/3`` of the same cell at
the same episode index (the same init state index and seed): the Δ is the mean of the paired
differences (perturbed - original, each -1, 0 or 1), with a percentile bootstrap interval, as
the main table pairs cells. Error rows are left out, and a pair with one side missing is not
counted. Overall: see :func:`overall`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from pipeline.results.aggregate import RIMG_EPS as EPS
from pipeline.results.aggregate import bootstrap_mean_ci, reference_cell
from workers.envs.suites.libero.pro.families import FAMILIES, ORIGINAL, split_suite

FAMILY_ORDER = (ORIGINAL, *FAMILIES)


def tag(episodes: pd.DataFrame) -> pd.DataFrame:
    """The episodes of LIBERO-PRO suites with ``base`` (the original suite), ``family`` and
    ``index`` (the task's index in its suite) columns; empty when the run has none of its
    perturbed suites."""
    df = episodes[episodes["error"].isna()].copy()

    def split(suite: object) -> tuple[str, str] | None:
        try:
            return split_suite(str(suite))
        except ValueError:
            return None

    parts = df["suite"].map(split)
    df = df[parts.notna()]
    if df.empty:
        return df
    parts = parts[parts.notna()]
    df["base"] = [p[0] for p in parts]
    df["family"] = [p[1] for p in parts]
    if not (df["family"] != ORIGINAL).any():
        return df.iloc[0:0]
    df["index"] = df["task_id"].str.rsplit("/", n=1).str[1]
    return df


@dataclass(frozen=True)
class FamilyEntry:
    """One suite x family entry of one cell."""

    n: int
    success: float
    delta: float | None = None  # vs the original, paired (None: the original itself or no pairs)
    ci_low: float | None = None
    ci_high: float | None = None
    n_pairs: int = 0


def _paired(df: pd.DataFrame, family: str) -> tuple[np.ndarray, int]:
    key = ["cell_id", "base", "index", "episode_index"]
    pert = df[df["family"] == family].set_index(key)["success"]
    orig = df[df["family"] == ORIGINAL].set_index(key)["success"]
    joined = pert.to_frame("p").join(orig.rename("o"), how="inner")
    d = joined["p"].astype(int).to_numpy() - joined["o"].astype(int).to_numpy()
    return d, len(d)


def _entry(df: pd.DataFrame, family: str) -> FamilyEntry:
    rows = df[df["family"] == family]
    success = float(rows["success"].mean()) if len(rows) else float("nan")
    if family == ORIGINAL:
        return FamilyEntry(len(rows), success)
    d, n = _paired(df, family)
    if not n:
        return FamilyEntry(len(rows), success)
    lo, hi = bootstrap_mean_ci(d)
    return FamilyEntry(len(rows), success, float(d.mean()), lo, hi, n)


def families_present(tagged: pd.DataFrame) -> list[str]:
    present = set(tagged["family"])
    ordered = [f for f in FAMILY_ORDER if f in present]
    return ordered + sorted(present - set(ordered))


def table(tagged: pd.DataFrame, cell: str) -> dict[str, dict[str, FamilyEntry]]:
    """base suite (and ``all``) -> family -> FamilyEntry, for one cell of the run."""
    df = tagged[tagged["cell_id"] == cell]
    fams = families_present(tagged)
    out: dict[str, dict[str, FamilyEntry]] = {}
    for base in sorted(df["base"].unique(), key=_suite_order):
        g = df[df["base"] == base]
        out[base] = {f: _entry(g, f) for f in fams if (g["family"] == f).any()}
    out["all"] = {f: _entry(df, f) for f in fams}
    return out


#: the families vla-eval's leaderboard averages (its ori, obj, pos, sem, task columns; env out)
OVERALL_FAMILIES = (ORIGINAL, "object", "swap", "lan", "task")
OVERALL_CELLS = 4 * len(OVERALL_FAMILIES)


def overall(tagged: pd.DataFrame, cell: str) -> tuple[float, int]:
    """(overall success, suite x family rates it averages) of one cell, by vla-eval's
    leaderboard rule (``leaderboard/scripts/refine.py::_compute_overall``): the plain mean of
    the 20 per-suite rates, 4 suites x {original, object, swap, lan, task}; the environment
    family and the ``with_*`` variants are left out, the originals are in. The leaderboard
    gives none unless all 20 are there; here the mean is over those present and the count
    says how many."""
    df = tagged[(tagged["cell_id"] == cell) & tagged["family"].isin(OVERALL_FAMILIES)]
    if df.empty:
        return float("nan"), 0
    rates = df.groupby(["base", "family"])["success"].mean()
    return float(rates.mean()), len(rates)


def r_img(tagged: pd.DataFrame, cell: str) -> dict[str, dict[str, float]]:
    """base suite (and ``all``) -> family -> R_img of the cell's episodes there: mean E_img /
    (mean E_img + mean E_prop + EPS) over the episodes' means, the paper's ratio of time
    averages as the heatmap computes it (not the mean of per-step ratios); absent where the
    cell computes no diagnostics."""
    df = tagged[tagged["cell_id"] == cell].dropna(subset=["e_img_mean", "e_prop_mean"])
    out: dict[str, dict[str, float]] = {}
    for base in [*sorted(df["base"].unique(), key=_suite_order), "all"]:
        g = df if base == "all" else df[df["base"] == base]
        m = g.groupby("family")[["e_img_mean", "e_prop_mean"]].mean()
        ratio = m["e_img_mean"] / (m["e_img_mean"] + m["e_prop_mean"] + EPS)
        out[base] = {str(f): float(v) for f, v in ratio.items()}
    return out


def cells(tagged: pd.DataFrame) -> list[str]:
    """The run's cells, the reference (baseline, else diagnose) first."""
    ref = reference_cell(set(tagged["cell_id"]))
    return sorted(tagged["cell_id"].unique(), key=lambda c: (c != ref, c))


def _suite_order(base: str) -> int:
    order = ("libero_spatial", "libero_object", "libero_goal", "libero_10")
    return order.index(base) if base in order else len(order)
