"""A study's comparisons, primary and exploratory: the endpoints its file declared before its
first episode (pipeline.planning.study), with Holm's correction over them, and every other
paired comparison of its runs, uncorrected and labelled exploratory.

A comparison is the success of one cell minus another's in one run, paired by episode
(``aggregate.paired_vs_baseline``: bootstrap 95% interval, exact McNemar p, the minimum
detectable effect at 80% power).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import pandas as pd

from pipeline.results import aggregate as agg
from pipeline.results.power import holm

if TYPE_CHECKING:
    from pipeline.planning.study import Endpoint


class RunRef(Protocol):
    """A study run as the report sees it (``pipeline.reporting.observations.RunRef``)."""

    run_dir: Path

    @property
    def label(self) -> str: ...


def _row(member: str, cell: str, reference: str, suite: str | None, d: agg.PairedDiff | None):
    row: dict[str, Any] = {"member": member, "cell": cell, "reference": reference, "suite": suite}
    if d is None:
        return row | {"n_pairs": 0, "diff": math.nan, "ci95": [math.nan, math.nan], "p": math.nan}
    return row | {
        "n_pairs": d.n_pairs,
        "diff": d.diff,
        "ci95": [d.ci_low, d.ci_high],
        "p": d.p_value,
        "mde_pp": d.mde_pp,
    }


def compare(episodes: pd.DataFrame, cell: str, reference: str, suite: str | None = None):
    """``cell`` against ``reference`` on their shared episodes (of ``suite`` when given)."""
    df = episodes[episodes["cell_id"].isin([cell, reference])]
    if suite is not None:
        df = df[df["suite"] == suite]
    found = [d for d in agg.paired_vs_baseline(df, baseline=reference) if d.cell_id == cell]
    return found[0] if found else None


def comparisons(refs: Sequence[RunRef], endpoints: Sequence[Endpoint]) -> dict[str, list[dict]]:
    """``{"primary": [...], "exploratory": [...]}``: each declared endpoint (a member not run,
    e.g. left out by --only, has no pairs) with its Holm-adjusted p over the primary family;
    then, per run, every cell against its reference cell (baseline, else diagnose) that is not
    a primary endpoint, raw p only."""
    from pipeline.reporting.run_data import load_run

    episodes = {r.label: load_run(r.run_dir).episodes for r in refs}
    primary = []
    for e in endpoints:
        eps = episodes.get(e.member)
        d = compare(eps, e.cell, e.reference, e.suite) if eps is not None else None
        primary.append(_row(e.member, e.cell, e.reference, e.suite, d) | {"ran": eps is not None})
    adjusted = holm([r["p"] for r in primary]) if primary else np.array([])
    for r, p in zip(primary, adjusted, strict=True):
        r["p_holm"] = float(p)
    declared = {(e.member, e.cell, e.reference) for e in endpoints if e.suite is None}
    exploratory = []
    for label, eps in episodes.items():
        ok = eps[eps["error"].isna()]
        reference = agg.reference_cell(set(ok["cell_id"]))
        for d in agg.paired_vs_baseline(eps, baseline=reference) if reference else []:
            if (label, d.cell_id, reference) not in declared:
                exploratory.append(_row(label, d.cell_id, str(reference), None, d))
    return {"primary": primary, "exploratory": exploratory}


def _pp(x: float) -> str:
    return "–" if not np.isfinite(x) else f"{100 * x:+.1f}"


def _p(x: float) -> str:
    return "–" if not np.isfinite(x) else f"{x:.3g}"


def _delta(r: dict) -> str:
    return f"{_pp(r['diff'])} [{_pp(r['ci95'][0])}, {_pp(r['ci95'][1])}]"


def markdown(result: dict[str, list[dict]], pinned: str | None) -> list[str]:
    """The primary section (Holm) and the exploratory one, as report lines."""
    primary, exploratory = result["primary"], result["exploratory"]
    lines = ["## Primary endpoints", ""]
    if not primary:
        lines += [
            "None declared: the study file has no `endpoints:` block, so every comparison "
            "below is exploratory.",
            "",
        ]
    else:
        lines += [
            f"Declared in the study file before its first episode ({len(primary)} "
            f"comparisons{f', hash {pinned[:12]}' if pinned else ''}); p-values adjusted by "
            "Holm's step-down over these comparisons (family-wise α = 0.05).",
            "",
            "| member | comparison | suite | Δ success pp (95% CI) | McNemar p | Holm p | pairs |",
            "|---|---|---|---|---|---|---|",
        ]
        for r in primary:
            pairs = r["n_pairs"] if r["ran"] else "not run"
            lines.append(
                f"| {r['member']} | {r['cell']} vs {r['reference']} | {r['suite'] or 'all'} | "
                f"{_delta(r)} | {_p(r['p'])} | {_p(r['p_holm'])} | {pairs} |"
            )
        lines.append("")
    lines += [
        "## Exploratory comparisons",
        "",
        "Not declared before the data: uncorrected p-values, to be read as hypotheses for a "
        "later study, not as findings (so are the sections after this one).",
        "",
        "| member | comparison | Δ success pp (95% CI) | McNemar p (uncorrected) | pairs |",
        "|---|---|---|---|---|",
    ]
    for r in exploratory:
        lines.append(
            f"| {r['member']} | {r['cell']} vs {r['reference']} | {_delta(r)} | {_p(r['p'])} "
            f"| {r['n_pairs']} |"
        )
    return [*lines, ""]
