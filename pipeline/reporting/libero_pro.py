"""The report's LIBERO-PRO section (``pipeline.results.libero_pro``): per cell, success by
original suite x perturbation family with the paired Δ against the original, the overall, and
R_img by suite x family (the paper's observation 1 on a standard benchmark)."""

from __future__ import annotations

import math

import pandas as pd

from pipeline.results import libero_pro as lp


def _pct(x: float | None) -> str:
    return "–" if x is None or math.isnan(x) else f"{100 * x:.1f}"


def _entry(c: lp.FamilyEntry) -> str:
    text = f"{_pct(c.success)} (n={c.n})"
    if c.delta is not None:
        text += f" Δ {100 * c.delta:+.1f} [{100 * c.ci_low:+.1f}, {100 * c.ci_high:+.1f}]"
    return text


def _md(headers: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def section(episodes: pd.DataFrame) -> list[str]:
    """The section's lines; none where the run has no LIBERO-PRO perturbed suite."""
    tagged = lp.tag(episodes)
    if tagged.empty:
        return []
    fams = lp.families_present(tagged)
    out = [
        "",
        "## LIBERO-PRO: success (%) by suite and perturbation, Δ vs the original (pp, 95% CI)",
        "",
        "Each perturbed task is paired with its original task in the same cell at the same "
        "episode index (same init state and seed). Overall: vla-eval's leaderboard rule, the "
        "mean of the 4 suites x {original, object, swap, lan, task} rates "
        "(docs/suites/libero_pro.md).",
    ]
    diagnosed = []
    for cell in lp.cells(tagged):
        t = lp.table(tagged, cell)
        rows = [[base, *(_entry(t[base][f]) if f in t[base] else "–" for f in fams)] for base in t]
        value, n = lp.overall(tagged, cell)
        partial = "" if n == lp.OVERALL_CELLS else f" (over {n} of {lp.OVERALL_CELLS} rates)"
        out += [
            "",
            f"**{cell}**: overall {_pct(value)}{partial}",
            "",
            _md(["suite", *fams], rows),
        ]
        if tagged.loc[tagged["cell_id"] == cell, "e_img_mean"].notna().any():
            diagnosed.append(cell)
    for cell in diagnosed:
        r = lp.r_img(tagged, cell)
        rows = [
            [
                base,
                *(
                    f"{v:.3g}" if not math.isnan(v := r[base].get(f, math.nan)) else "–"
                    for f in fams
                ),
            ]
            for base in r
        ]
        out += [
            "",
            f"**R_img by suite and perturbation, {cell}** (mean E_img / (mean E_img + mean E_prop))",
            "",
            _md(["suite", *fams], rows),
        ]
    return out
