"""From the episodes table to the numbers a paper reports, with honest uncertainty.

- success per task, per suite and overall, with Wilson 95% intervals;
- for chain tasks (subtasks_total > 1): the i/N completion rates and Avg Len (mean completed
  subtasks, CALVIN-style), with a bootstrap interval;
- completion time: simulated seconds to success over successful episodes, and wall seconds;
- per cell, the paired difference against the baseline cell on identical keys
  (task_id, episode_index): exact McNemar p-value (binomial test on discordant pairs), a
  bootstrap interval of the mean difference, and what the comparison could detect: its minimum
  detectable effect and the pairs it would need for 1 pp and 5 pp (``power``: McNemar at 80%
  power and two-sided alpha = 0.05, Connor 1987, from its own discordance rate).

Error rows are excluded from every rate and counted apart.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd
import pyarrow as pa

# scipy.special, not scipy.stats: the same numbers (tested against binomtest), and it imports
# in a fraction of the time (scipy.stats was ~3 s of every `idr-eval report` here)
from scipy.special import bdtr, ndtri

from pipeline.results.power import paired_power

Z95 = 0.95
MULTINOMIAL_MAX_DISTINCT = 64  # bootstrap by counts per distinct value up to this many values


#: The rate columns of the success tables (``_rate_rows``).
RATE_COLUMNS = ("success_rate", "ci_low", "ci_high")


# the floor of R_img = mean E_img / (mean E_img + mean E_prop + RIMG_EPS) wherever it is computed
RIMG_EPS = 1e-6


def wilson(successes: int, n: int, confidence: float = Z95) -> tuple[float, float]:
    """Wilson score interval of successes / n (without continuity correction)."""
    if n == 0:
        return (float("nan"), float("nan"))
    z = float(ndtri(1 - (1 - confidence) / 2))
    p, z2 = successes / n, z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z * np.sqrt(p * (1 - p) / n + z2 / (4 * n * n)) / (1 + z2 / n)
    return (float(max(0.0, centre - half)), float(min(1.0, centre + half)))


def bootstrap_means(values: np.ndarray, n_boot: int, rng: np.random.Generator) -> np.ndarray:
    """``n_boot`` means of ``values`` resampled with replacement.

    Episode outcomes take few distinct values (success 0/1, subtasks done 0..5, paired
    differences -1/0/1): resampling n of them is then drawing how many of each value from a
    multinomial(n, their shares), the same distribution of resampled means at O(n_boot x
    distinct values) instead of O(n_boot x n) (a 50,000-episode cell: 2,000 x 3 numbers, not
    2,000 x 50,000). Many distinct values: plain index resampling."""
    values = np.asarray(values, dtype=float)
    distinct, counts = np.unique(values, return_counts=True)
    if distinct.size <= MULTINOMIAL_MAX_DISTINCT:
        draws = rng.multinomial(values.size, counts / values.size, size=n_boot)
        return draws @ distinct / values.size
    idx = rng.integers(0, values.size, size=(n_boot, values.size))
    return values[idx].mean(axis=1)


def bootstrap_mean_ci(
    values: np.ndarray, n_boot: int = 2000, confidence: float = Z95, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean (see ``bootstrap_means``)."""
    values = np.asarray(values, dtype=float)
    if values.size == 0:
        return (float("nan"), float("nan"))
    means = bootstrap_means(values, n_boot, np.random.default_rng(seed))
    lo, hi = np.quantile(means, [(1 - confidence) / 2, 1 - (1 - confidence) / 2])
    return (float(lo), float(hi))


def mcnemar_exact(b: int, c: int) -> float:
    """Two-sided exact McNemar p-value from the discordant counts b (only A) and c (only B)."""
    if b + c == 0:
        return 1.0
    # binomial(b + c, 1/2) is symmetric: twice the lower tail of the smaller count
    return float(min(1.0, 2.0 * bdtr(min(b, c), b + c, 0.5)))


def _frame(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    return episodes.to_pandas() if isinstance(episodes, pa.Table) else episodes.copy()


def _rate_rows(df: pd.DataFrame, by: list[str]) -> pd.DataFrame:
    ok = df[df["error"].isna()]
    errs = df[df["error"].notna()].groupby(by).size().rename("errors")
    g = ok.groupby(by)
    out = pd.DataFrame({"n": g.size(), "successes": g["success"].sum().astype(int)})
    out = out.join(errs, how="outer").fillna({"n": 0, "successes": 0, "errors": 0})
    out[["n", "successes", "errors"]] = out[["n", "successes", "errors"]].astype(int)
    out["success_rate"] = np.where(out["n"] > 0, out["successes"] / out["n"].clip(lower=1), np.nan)
    cis = [wilson(s, n) for s, n in zip(out["successes"], out["n"], strict=True)]
    out["ci_low"] = [c[0] for c in cis]
    out["ci_high"] = [c[1] for c in cis]
    return out.reset_index()


def success_by_task(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    return _rate_rows(_frame(episodes), ["cell_id", "suite", "task_id"])


def success_by_suite(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    return _rate_rows(_frame(episodes), ["cell_id", "suite"])


def any_perturbed(episodes: pd.DataFrame) -> bool:
    """Whether any episode ran under a perturbation."""
    return bool((perturbation_labels(episodes) != "none").any())


def perturbation_labels(df: pd.DataFrame) -> pd.Series:
    """Each row's perturbation as ``kind:severity`` (``none`` for none), from the
    ``perturbation`` and ``severity`` columns; rows without them (run dirs written before the
    columns existed) are read off their task ids (``task@kind:severity``)."""
    from workers.envs.wrappers.perturbation_grammar import Perturbation, perturbation_of

    from_ids = df["task_id"].astype(str).map(perturbation_of)
    if "perturbation" not in df:
        return from_ids
    sevs = df["severity"] if "severity" in df else pd.Series([None] * len(df), index=df.index)

    def label(kind: object, severity: object, from_id: str) -> str:
        if not isinstance(kind, str):
            return from_id  # an old row: no columns
        if kind == "none" or ":" in kind:  # none, or already a label (a tagged frame)
            return kind
        return Perturbation(kind, float(severity)).text  # type: ignore[arg-type]

    labels = [label(*t) for t in zip(df["perturbation"], sevs, from_ids, strict=True)]
    return pd.Series(labels, index=df.index, dtype=object)


def as_percent(df: pd.DataFrame, columns: tuple[str, ...] = RATE_COLUMNS) -> pd.DataFrame:
    """A copy of ``df`` with its rate ``columns`` in percent (the unit of success everywhere:
    report, MLflow, compare)."""
    df = df.copy()
    for c in columns:
        if c in df:
            df[c] = 100.0 * df[c]
    return df


def with_perturbation(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` with its ``perturbation`` column as a label, ``kind:severity`` or ``none``."""
    out = df.copy()
    out["perturbation"] = perturbation_labels(df)
    return out


def success_by_perturbation(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    """Success per cell and perturbation (over the tasks and suites the perturbation spans)."""
    return _rate_rows(with_perturbation(_frame(episodes)), ["cell_id", "perturbation"])


def success_overall(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    return _rate_rows(_frame(episodes), ["cell_id"])


def chain_metrics(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    """Per cell and chain task: i/N rates (share of chains with >= i subtasks) and Avg Len."""
    df = _frame(episodes)
    df = df[df["error"].isna() & (df["subtasks_total"].fillna(1) > 1)]
    rows = []
    for (cell, suite, task), g in df.groupby(["cell_id", "suite", "task_id"]):
        total = int(g["subtasks_total"].max())
        done = g["subtasks_done"].to_numpy(dtype=float)
        lo, hi = bootstrap_mean_ci(done)
        row = {
            "cell_id": cell,
            "suite": suite,
            "task_id": task,
            "n": len(g),
            "subtasks_total": total,
            "avg_len": float(done.mean()),
            "avg_len_low": lo,
            "avg_len_high": hi,
        }
        for i in range(1, total + 1):
            row[f"rate_{i}of{total}"] = float((done >= i).mean())
        rows.append(row)
    return pd.DataFrame(rows)


def completion_times(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    """Mean simulated seconds to success (successful episodes) and mean wall seconds (all)."""
    df = _frame(episodes)
    df = df[df["error"].isna()]
    rows = []
    for (cell, suite), g in df.groupby(["cell_id", "suite"]):
        s = g[g["success"]]
        rows.append(
            {
                "cell_id": cell,
                "suite": suite,
                "sim_seconds_to_success": float(s["sim_seconds"].mean())
                if len(s)
                else float("nan"),
                "wall_seconds_mean": float(g["wall_seconds"].mean()),
                "inference_ms_mean": float(g["inference_ms_mean"].mean()),
            }
        )
    return pd.DataFrame(rows)


@dataclass(frozen=True)
class PairedDiff:
    cell_id: str
    n_pairs: int
    diff: float  # success(cell) - success(baseline) on the shared keys
    ci_low: float
    ci_high: float
    p_value: float
    only_cell: int  # discordant: cell succeeded, baseline failed
    only_baseline: int
    # what the comparison could detect (power.paired_power: McNemar, 80% power, alpha = 0.05,
    # at its own discordance rate): inf where nothing is / no number of pairs would be,
    # nan without pairs; power_note says why
    mde_pp: float = float("nan")  # minimum detectable |difference|, percentage points
    pairs_for_1pp: float = float("nan")  # pairs needed for a 1 pp difference
    pairs_for_5pp: float = float("nan")  # ... for 5 pp
    power_note: str = ""


def reference_cell(cells: set[str]) -> str | None:
    """The cell others are compared with: ``baseline``, else ``diagnose`` (it executes the base
    action, so with shared noise it is the baseline too)."""
    for name in ("baseline", "diagnose"):
        if name in cells:
            return name
    return None


def paired_vs_baseline(
    episodes: pa.Table | pd.DataFrame, baseline: str | None = None, n_boot: int = 2000
) -> list[PairedDiff]:
    df = _frame(episodes)
    df = df[df["error"].isna()]
    baseline = baseline or reference_cell(set(df["cell_id"]))
    if baseline is None or baseline not in set(df["cell_id"]):
        return []
    key = ["suite", "task_id", "episode_index"]
    base = df[df["cell_id"] == baseline].set_index(key)["success"]
    out = []
    for cell, g in df[df["cell_id"] != baseline].groupby("cell_id"):
        joined = g.set_index(key)["success"].to_frame("cell").join(base.rename("base"), how="inner")
        d = joined["cell"].astype(int).to_numpy() - joined["base"].astype(int).to_numpy()
        lo, hi = bootstrap_mean_ci(d, n_boot=n_boot)
        b, c = int((d == 1).sum()), int((d == -1).sum())
        pw = paired_power(len(d), b + c)
        out.append(
            PairedDiff(
                str(cell),
                len(d),
                float(d.mean()) if len(d) else float("nan"),
                lo,
                hi,
                mcnemar_exact(b, c),
                b,
                c,
                mde_pp=pw.mde_pp,
                pairs_for_1pp=pw.pairs_for_1pp,
                pairs_for_5pp=pw.pairs_for_5pp,
                power_note=pw.note,
            )
        )
    return out


def diagnostics_by_cell(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    df = _frame(episodes)
    df = df[df["error"].isna()]
    cols = ["gate_rate", "e_img_mean", "e_prop_mean", "r_img_mean"]
    return df.groupby("cell_id")[cols].mean().reset_index()


FAILURE_KEYS = ("cell_id", "task_id", "n", "failed")  # failure_causes' columns before the causes


def failure_causes(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    """Failed episodes per cell and task, counted by cause (error rows are not failures).

    Columns: cell_id, task_id, n (episodes without error), failed, then one count per cause
    (``timeout`` and the env's own codes), most frequent first; empty when nothing failed.
    Episodes stored before the ``failure`` column existed count as ``unknown``."""
    df = _frame(episodes)
    df = df[df["error"].isna()]
    if "failure" not in df:
        df = df.assign(failure=None)
    failed = df[~df["success"].astype(bool)]
    if failed.empty:
        return pd.DataFrame(columns=list(FAILURE_KEYS))
    causes = failed["failure"].fillna("unknown")
    counts = pd.crosstab([failed["cell_id"], failed["task_id"]], causes)
    counts = counts[counts.sum().sort_values(ascending=False, kind="stable").index]
    n = df.groupby(["cell_id", "task_id"]).size().rename("n")
    out = counts.join(n, how="left")
    out.insert(0, "failed", counts.sum(axis=1))
    out.insert(0, "n", out.pop("n"))
    out.columns.name = None
    return out.reset_index()


def errors(episodes: pa.Table | pd.DataFrame) -> pd.DataFrame:
    df = _frame(episodes)
    return df[df["error"].notna()][["cell_id", "task_id", "episode_index", "attempt", "error"]]


def steps_summary(steps: pa.Table, bins: int = 10) -> tuple[pa.Table, pa.Table]:
    """Per-inference diagnostics, aggregated with Arrow (fast on tens of millions of rows).

    Returns (per cell: inferences, mean E_img / E_prop / R_img, gate rate) and
    (per cell and normalized-progress bin: the same means), where progress is the inference's
    control step over its episode's last inference step.
    """
    import pyarrow.compute as pc

    means = [("e_img", "mean"), ("e_prop", "mean"), ("r_img", "mean"), ("gate", "mean")]
    per_cell = steps.group_by("cell_id").aggregate([("step", "count"), *means])
    per_cell = per_cell.rename_columns(
        [
            "cell_id"
            if n == "cell_id"
            else n.replace("_mean", "").replace("step_count", "inferences")
            for n in per_cell.column_names
        ]
    )
    key = ["cell_id", "task_id", "episode_index"]
    last = steps.group_by(key).aggregate([("step", "max")])
    joined = steps.select([*key, "step", "e_img", "e_prop", "r_img", "gate"]).join(last, key)
    denom = pc.max_element_wise(joined["step_max"], 1)
    progress = pc.divide(pc.cast(joined["step"], pa.float64()), pc.cast(denom, pa.float64()))
    b = pc.min_element_wise(pc.cast(pc.floor(pc.multiply(progress, bins)), pa.int64()), bins - 1)
    joined = joined.append_column("progress_bin", b)
    per_bin = joined.group_by(["cell_id", "progress_bin"]).aggregate(means)
    per_bin = per_bin.sort_by([("cell_id", "ascending"), ("progress_bin", "ascending")])
    return per_cell, per_bin
