"""Training seeds as a random effect: figures pooled over a member's training seeds with a
two-level bootstrap.

A member of a study (an architecture in an environment) may be trained several times with
different seeds. Its episodes are then not one sample: two seeds of one architecture can differ
as much as two architectures do, and an interval that resamples episodes only says nothing
about a third seed. Here:

- the **pooled** figure is the mean of the per-seed figures (each seed weighs the same,
  whatever its episode count);
- its **95% interval** resamples at two levels, as the data were made: training seeds with
  replacement, then, within each drawn seed, its episodes with replacement inside each task
  (tasks are fixed: every seed ran the same ones). A seed drawn twice gets two independent
  episode resamples;
- a paired effect's **p** is the two-sided bootstrap p of the pooled difference (twice the
  smaller share of replicates on either side of zero), since McNemar's test holds the seeds
  fixed. With two seeds the seed level has three outcomes, so the interval is wide: that is
  what two seeds can say.

With one seed the two-level bootstrap is the ordinary (task-stratified) episode bootstrap.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
import pandas as pd

N_BOOT = 2000
EPS = 1e-6  # R_img's epsilon (pipeline.results.aggregate.RIMG_EPS)


@dataclass(frozen=True)
class Pooled:
    """A figure per seed and pooled over the seeds, with its two-level 95% interval."""

    per_seed: dict[int, float]
    value: float  # mean over seeds
    ci95: tuple[float, float]
    p: float = math.nan  # paired effects: two-sided bootstrap p of value == 0
    units: int = 0  # episodes (or pairs) behind it, all seeds together

    @property
    def seeds(self) -> int:
        return len(self.per_seed)

    def record(self) -> dict:
        return {
            "seeds": self.seeds,
            "per_seed": {str(k): v for k, v in sorted(self.per_seed.items())},
            "value": self.value,
            "ci95": list(self.ci95),
            "p": self.p,
            "units": self.units,
        }


# A seed's data: one row per unit (episode or pair) with a task and the columns a statistic reads.
Statistic = Callable[[dict[str, np.ndarray]], np.ndarray]


def _replicates(
    frame: pd.DataFrame, columns: list[str], stat: Statistic, draws: int, rng: np.random.Generator
) -> np.ndarray:
    """``draws`` bootstrap values of ``stat`` on ``frame``, its units resampled within tasks.
    ``stat`` takes {column: (draws, n) array} and returns (draws,)."""
    parts: dict[str, list[np.ndarray]] = {c: [] for c in columns}
    for _, g in frame.groupby("task_id", sort=True):
        n = len(g)
        idx = rng.integers(0, n, size=(draws, n))
        for c in columns:
            parts[c].append(g[c].to_numpy(dtype=float)[idx])
    return stat({c: np.concatenate(v, axis=1) for c, v in parts.items()})


def two_level(
    by_seed: Mapping[int, pd.DataFrame],
    columns: list[str],
    stat: Statistic,
    n_boot: int = N_BOOT,
    seed: int = 0,
    paired: bool = False,
) -> Pooled:
    """``stat`` per seed, pooled (mean over seeds) with its two-level bootstrap interval (and
    p when ``paired``: the statistic is a difference whose null is zero)."""
    seeds = sorted(s for s, f in by_seed.items() if len(f))
    if not seeds:
        return Pooled({}, math.nan, (math.nan, math.nan))
    point = {
        s: float(stat({c: by_seed[s][c].to_numpy(dtype=float)[None, :] for c in columns})[0])
        for s in seeds
    }
    rng = np.random.default_rng(seed)
    k = len(seeds)
    # each (replicate, slot) of a seed draw gets its own episode resample of the drawn seed
    inner = {s: _replicates(by_seed[s], columns, stat, n_boot * k, rng) for s in seeds}
    drawn = rng.integers(0, k, size=(n_boot, k))
    slot = np.arange(n_boot)[:, None] * k + np.arange(k)[None, :]
    table = np.stack([inner[s] for s in seeds])  # (k seeds, n_boot * k)
    boots = np.nanmean(table[drawn, slot], axis=1)
    value = float(np.mean(list(point.values())))
    lo, hi = (float(np.nanquantile(boots, q)) for q in (0.025, 0.975))
    p = math.nan
    if paired:
        below, above = float(np.mean(boots <= 0)), float(np.mean(boots >= 0))
        p = min(1.0, 2 * min(below, above))
    units = sum(len(by_seed[s]) for s in seeds)
    return Pooled(point, value, (lo, hi), p, units)


# -- the statistics a study pools ---------------------------------------------------------------
def _mean(col: str) -> Statistic:
    return lambda a: a[col].mean(axis=1)


def _rimg(a: dict[str, np.ndarray]) -> np.ndarray:
    s_img, s_prop = a["s_img"].sum(axis=1), a["s_prop"].sum(axis=1)
    return s_img / (s_img + s_prop + EPS)


def _diff(a: dict[str, np.ndarray]) -> np.ndarray:
    return (a["cell"] - a["base"]).mean(axis=1)


def pooled_success(episodes_by_seed: Mapping[int, pd.DataFrame], cell: str) -> Pooled:
    """Success rate of ``cell`` (episodes without an error) per seed and pooled."""
    frames = {
        s: e.loc[(e["cell_id"] == cell) & e["error"].isna(), ["task_id", "success"]].astype(
            {"success": float}
        )
        for s, e in episodes_by_seed.items()
    }
    return two_level(frames, ["success"], _mean("success"))


def pooled_rimg(steps_by_seed: Mapping[int, pd.DataFrame]) -> Pooled:
    """R_img (ratio of mean effects, as everywhere) of each seed's diagnose steps, pooled;
    episodes are the units resampled (steps of one episode are not independent)."""
    frames = {}
    for s, steps in steps_by_seed.items():
        per_ep = steps.groupby(["task_id", "episode_index"])[["e_img", "e_prop"]].sum()
        frames[s] = per_ep.rename(columns={"e_img": "s_img", "e_prop": "s_prop"}).reset_index()
    return two_level(frames, ["s_img", "s_prop"], _rimg)


def paired_frame(episodes: pd.DataFrame, cell: str, reference: str) -> pd.DataFrame:
    """One seed's pairs: (task_id, cell success, reference success) on shared episodes."""
    ok = episodes[episodes["error"].isna()]
    key = ["suite", "task_id", "episode_index"]
    a = ok[ok["cell_id"] == cell].set_index(key)["success"].rename("cell")
    b = ok[ok["cell_id"] == reference].set_index(key)["success"].rename("base")
    joined = a.to_frame().join(b, how="inner").reset_index()
    return joined[["task_id", "cell", "base"]].astype({"cell": float, "base": float})


def pooled_paired(
    episodes_by_seed: Mapping[int, pd.DataFrame], cell: str, reference: str
) -> Pooled:
    """success(cell) - success(reference), paired by episode within each seed, pooled over
    seeds with its two-level interval and bootstrap p."""
    frames = {s: paired_frame(e, cell, reference) for s, e in episodes_by_seed.items()}
    return two_level(frames, ["cell", "base"], _diff, paired=True)
