"""What MLflow gets as numbers and tables: per-cell metrics (success in percent, Avg Len, times,
diagnostics, Δ vs baseline in points), rounded to 4 significant figures, and the per-task
tables. Computed from the same aggregation as the report (pipeline.results.aggregate)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pandas as pd

from pipeline.results import aggregate as agg


def rounded(value: float) -> float:
    """``value`` to SIG_FIGS significant figures; integers (counts) unchanged."""
    value = float(value)
    return value if value.is_integer() else float(f"{value:.{SIG_FIGS}g}")


def finite_only(metrics: dict[str, float]) -> dict[str, float]:
    return {k: rounded(v) for k, v in metrics.items() if v is not None and math.isfinite(float(v))}


def metric_key(*parts: str) -> str:
    # MLflow keys allow alphanumerics, _ - . space / ; map anything else to _
    return "/".join("".join(c if c.isalnum() or c in "_-. " else "_" for c in p) for p in parts)


def plain_value(value: Any) -> str:
    return getattr(value, "text", None) or str(value)


def task_tables(
    episodes: pd.DataFrame, out: Path, chains: pd.DataFrame | None = None
) -> list[Path]:
    """Per-task success (and chain i/N rates) of every cell as CSV files in ``out``: the per-task
    numbers the UI shows as the parent run's artifacts, one file whatever the grid's size.
    ``chains``: ``agg.chain_metrics(episodes)`` where the caller has it already."""
    paths = [out / "success_by_task.csv"]
    agg.as_percent(agg.success_by_task(episodes)).to_csv(paths[0], index=False)
    chains = agg.chain_metrics(episodes) if chains is None else chains
    if not chains.empty:
        paths.append(out / "chains_by_task.csv")
        chains.to_csv(paths[-1], index=False)
    return paths


def _avg_len(chains: pd.DataFrame) -> float:
    """Avg Len over chain tasks, each weighted by its number of chains."""
    return float((chains["avg_len"] * chains["n"]).sum() / chains["n"].sum())


def cell_metrics(
    episodes: pd.DataFrame, chains: pd.DataFrame | None = None
) -> dict[str, dict[str, float]]:
    """Per cell: success (%) overall and per suite, Avg Len overall and per suite, completion
    times, diagnostics, Δ vs baseline (percentage points), failed episodes by cause. Names are bounded by the number of
    suites and failure causes, never by tasks or episodes (see ``task_tables``)."""
    out: dict[str, dict[str, float]] = {c: {} for c in episodes["cell_id"].unique()}
    for r in agg.success_overall(episodes).itertuples():
        out[r.cell_id].update(
            success=100 * r.success_rate,
            success_ci_low=100 * r.ci_low,
            success_ci_high=100 * r.ci_high,
            episodes=r.n,
            errors=r.errors,
        )
    suites = agg.success_by_suite(episodes)
    for r in suites.itertuples():
        out[r.cell_id][metric_key("success", r.suite)] = 100 * r.success_rate
    for cell, g in suites.groupby("cell_id"):  # the paper's Avg: the mean of the suites' rates
        out[cell]["success_avg"] = 100 * float(g["success_rate"].mean())
    if agg.any_perturbed(episodes):
        for r in agg.success_by_perturbation(episodes).itertuples():
            out[r.cell_id][metric_key("success", "perturbation", r.perturbation)] = (
                100 * r.success_rate
            )
    # per task: in the parent's tables/ artifacts and the report, not as metrics (a metric
    # name per task would grow with the benchmark: 130 for LIBERO, thousands of sequences)
    chains = agg.chain_metrics(episodes) if chains is None else chains
    if not chains.empty:
        for (cell, suite), g in chains.groupby(["cell_id", "suite"]):
            out[cell][metric_key("avg_len", suite)] = _avg_len(g)
        for cell, g in chains.groupby("cell_id"):
            out[cell]["avg_len"] = _avg_len(g)
    for r in agg.completion_times(episodes).itertuples():
        out[r.cell_id][metric_key("sim_seconds_to_success", r.suite)] = r.sim_seconds_to_success
        out[r.cell_id]["wall_seconds_per_episode"] = r.wall_seconds_mean
        out[r.cell_id]["inference_ms"] = r.inference_ms_mean
    for r in agg.diagnostics_by_cell(episodes).itertuples():
        out[r.cell_id].update(
            gate_rate=r.gate_rate, e_img=r.e_img_mean, e_prop=r.e_prop_mean, r_img=r.r_img_mean
        )
    causes = agg.failure_causes(episodes)
    for cell, g in causes.groupby("cell_id"):  # failed episodes by cause, over the cell's tasks
        for cause in causes.columns[len(agg.FAILURE_KEYS) :]:
            out[cell][metric_key("failures", cause)] = float(g[cause].sum())
    for d in agg.paired_vs_baseline(episodes):
        out[d.cell_id].update(
            delta_vs_baseline=100 * d.diff,  # percentage points
            delta_ci_low=100 * d.ci_low,
            delta_ci_high=100 * d.ci_high,
            delta_p_value=d.p_value,
        )
    return out


def cells_table(per_cell: dict[str, dict[str, float]]) -> pd.DataFrame:
    """``cell_metrics`` as one table, a row per cell (the parent run's ``tables/cells.csv``):
    the per-cell numbers in one artifact rather than metric names that grow with the grid."""
    rows = [{"cell": c, **{k: rounded(v) for k, v in m.items()}} for c, m in per_cell.items()]
    return pd.DataFrame(rows).sort_values("cell", kind="stable")


#: Significant figures of every logged metric: a success of 36.666666666666664 % shows whole
#: in the UI's narrow columns as 36.67 (counts are kept exact).
SIG_FIGS = 4
