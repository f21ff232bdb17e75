"""The methods table: test-time methods side by side per backbone x suite, each with its
success, its paired difference against the reference cell (baseline, else diagnose) and
against IDR's mode E (with the minimum detectable effect at 80% power of each pairing,
``pipeline.results.power``), and what it cost per executed env step (rows of the base's forward and
inference ms), since methods infer at different rates."""

from __future__ import annotations

import math

import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc

from pipeline.results import aggregate as agg

HEADERS = [
    "backbone",
    "suite",
    "cell",
    "mode",
    "success % [95% CI]",
    "Δ vs {ref} pp [95% CI], p",
    "Δ vs E pp [95% CI], p",
    "rows / env step",
    "ms / env step",
]


def method_costs(steps: pa.Table) -> pd.DataFrame:
    """Per cell: the base's forward rows and the inference ms per executed env step (sums over
    the cell's inferences; NaN where the run dir predates the columns)."""
    cols = ("cell_id", "pass_rows", "executed_steps", "inference_ms")
    if steps.num_rows == 0 or any(c not in steps.column_names for c in cols):
        return pd.DataFrame(columns=["rows_per_step", "ms_per_step"])
    out = {}
    for cell in pc.unique(steps["cell_id"]).to_pylist():
        t = steps.filter(pc.equal(steps["cell_id"], cell))
        executed = pc.sum(t["executed_steps"]).as_py() or 0
        rows = pc.sum(t["pass_rows"]).as_py()
        ms = pc.sum(t["inference_ms"]).as_py()
        out[cell] = {
            "rows_per_step": rows / executed if executed and rows is not None else math.nan,
            "ms_per_step": ms / executed if executed and ms is not None else math.nan,
        }
    return pd.DataFrame.from_dict(out, orient="index")


def pairings_vs_e(g: pd.DataFrame) -> dict[str, agg.PairedDiff]:
    """Each cell paired with an E cell: the one of its own alpha where the grid has several
    (a dose-response: random at alpha a against E at a), else the first."""
    e_alpha = (
        g[g["mode"] == "E"].groupby("cell_id")["alpha"].first().sort_index()
        if "alpha" in g
        else pd.Series(dtype=float)
    )
    if e_alpha.empty:
        return {}
    out: dict[str, agg.PairedDiff] = {}
    same_alpha: dict[str, bool] = {}
    for e_cell, alpha in e_alpha.items():
        for d in agg.paired_vs_baseline(g, baseline=e_cell):
            same = math.isclose(g.loc[g["cell_id"] == d.cell_id, "alpha"].iloc[0], alpha)
            if d.cell_id not in out or (same and not same_alpha[d.cell_id]):
                out[d.cell_id], same_alpha[d.cell_id] = d, same
    return out


def _diff(d: dict[str, object] | None) -> str:
    """A pairing of ``methods_summary`` as the table shows it."""
    if d is None:
        return "–"
    lo, hi = d["ci95"]
    # "none": no effect this pairing's size and discordance could detect at 80% power
    mde = ", MDE none" if d["mde_pp"] is None else f", MDE {d['mde_pp']:.0f}"
    return (
        f"{100 * d['diff']:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}], "
        f"p={d['mcnemar_p']:.2g} (n={d['n_pairs']}{mde})"
    )


def _fmt(x: float | None, digits: int) -> str:
    return "–" if x is None or math.isnan(x) else f"{x:.{digits}f}"


def methods_table(
    episodes: pd.DataFrame, steps: pa.Table
) -> tuple[str, list[str], list[list[object]]] | None:
    """(title, headers, rows) of :func:`methods_summary`, or None for a run with fewer than
    two methods beside its reference cell (the main table says it all then)."""
    if episodes.loc[episodes["error"].isna(), "mode"].nunique() < 3:
        return None
    rows: list[list[object]] = []
    ref_name = "reference"
    for run in methods_summary(episodes, steps):
        ref_name = run["reference"] or ref_name
        for c in run["cells"]:
            lo, hi = c["ci95"]
            rows.append(
                [
                    run["backbone"],
                    run["suite"],
                    c["cell"],
                    c["mode"],
                    f"{100 * c['success']:.1f} [{100 * lo:.1f}, {100 * hi:.1f}]",
                    _diff(c["vs_reference"]),
                    _diff(c["vs_E"]),
                    _fmt(c["rows_per_step"], 2),
                    _fmt(c["ms_per_step"], 1),
                ]
            )
    headers = [h.format(ref=ref_name) for h in HEADERS]
    return ("Test-time methods side by side", headers, rows)


def _pairing(d: agg.PairedDiff | None) -> dict[str, object] | None:
    if d is None:
        return None
    return {
        "n_pairs": d.n_pairs,
        "diff": d.diff,
        "ci95": [d.ci_low, d.ci_high],
        "mcnemar_p": d.p_value,
        "only_cell": d.only_cell,
        "only_reference": d.only_baseline,
        "mde_pp": d.mde_pp if math.isfinite(d.mde_pp) else None,
    }


def methods_summary(episodes: pd.DataFrame, steps: pa.Table) -> list[dict[str, object]]:
    """The methods table as data, per backbone x suite: each cell's success with its Wilson
    interval, its pairings against the reference cell and against E (bootstrap interval,
    McNemar p, minimum detectable effect), and its cost per executed env step."""
    ok = episodes[episodes["error"].isna()]
    costs = method_costs(steps)
    out: list[dict[str, object]] = []
    for (backbone, suite), g in ok.groupby(["backbone", "suite"], sort=True):
        ref = agg.reference_cell(set(g["cell_id"]))
        vs_ref = {d.cell_id: d for d in agg.paired_vs_baseline(g, baseline=ref)} if ref else {}
        vs_e = pairings_vs_e(g)
        overall = agg.success_overall(g).set_index("cell_id")
        cells = []
        for cell in sorted(overall.index, key=lambda c: (c != ref, c)):
            o = overall.loc[cell]
            rows = g[g["cell_id"] == cell]
            cost = costs.loc[cell] if cell in costs.index else None
            cells.append(
                {
                    "cell": cell,
                    "mode": str(rows["mode"].iloc[0]),
                    "alpha": float(rows["alpha"].iloc[0]),
                    "episodes": len(rows),
                    "successes": int(rows["success"].sum()),
                    "success": float(o["success_rate"]),
                    "ci95": [float(o["ci_low"]), float(o["ci_high"])],
                    "vs_reference": _pairing(vs_ref.get(cell)),
                    "vs_E": _pairing(vs_e.get(cell)),
                    "rows_per_step": None if cost is None else _finite(cost["rows_per_step"]),
                    "ms_per_step": None if cost is None else _finite(cost["ms_per_step"]),
                }
            )
        out.append(
            {
                "backbone": backbone,
                "suite": suite,
                "reference": ref,
                "E": sorted(set(g.loc[g["mode"] == "E", "cell_id"])) or None,
                "tasks": sorted(set(g["task_id"])),
                "cells": cells,
            }
        )
    return out


def _finite(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
