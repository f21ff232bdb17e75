"""A study's comparisons, primary and exploratory: the endpoints its file declared before its
first episode (pipeline.planning.study), with Holm's correction over them, and every other
paired comparison of its runs, uncorrected and labelled exploratory.

A comparison is the success of one cell minus another's in one run, paired by episode
(``aggregate.paired_vs_baseline``: bootstrap 95% interval, exact McNemar p, the minimum
detectable effect at 80% power). For a member trained with several seeds (one run per seed) it
is pooled over the seeds: the mean of the per-seed differences, its two-level bootstrap
interval and p (``pipeline.results.seeds``); its minimum detectable effect is McNemar's on all
its pairs, which holds the seeds fixed, so it is a lower bound there.
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
    seed: int | None

    @property
    def label(self) -> str: ...

    @property
    def member(self) -> str: ...


def _row(member: str, cell: str, reference: str, suite: str | None, d: agg.PairedDiff | None):
    row: dict[str, Any] = {
        "member": member,
        "cell": cell,
        "reference": reference,
        "suite": suite,
        "seeds": 1,
        "test": "McNemar",
    }
    if d is None:
        return row | {"n_pairs": 0, "diff": math.nan, "ci95": [math.nan, math.nan], "p": math.nan}
    return row | {
        "n_pairs": d.n_pairs,
        "diff": d.diff,
        "ci95": [d.ci_low, d.ci_high],
        "p": d.p_value,
        "mde_pp": d.mde_pp,
    }


def _pooled_row(
    member: str, cell: str, reference: str, suite: str | None, by_seed: dict[int, pd.DataFrame]
) -> dict[str, Any]:
    """``cell`` against ``reference`` pooled over a member's training seeds (two-level
    bootstrap), with each seed's difference and McNemar's MDE on all pairs (a lower bound)."""
    from pipeline.results.seeds import pooled_paired

    frames = {s: _of_suite(e, suite) for s, e in by_seed.items()}
    pooled = pooled_paired(frames, cell, reference)
    mde = [compare(e, cell, reference) for e in frames.values()]
    return {
        "member": member,
        "cell": cell,
        "reference": reference,
        "suite": suite,
        "seeds": pooled.seeds,
        "test": "two-level bootstrap",
        "n_pairs": pooled.units,
        "diff": pooled.value,
        "ci95": list(pooled.ci95),
        "p": pooled.p,
        "per_seed": {str(k): v for k, v in sorted(pooled.per_seed.items())},
        "mde_pp": _pooled_mde(mde),
    }


def _pooled_mde(per_seed: list[agg.PairedDiff | None]) -> float:
    """McNemar's MDE on all the seeds' pairs together (seeds held fixed: a lower bound)."""
    from pipeline.results.power import paired_power

    found = [d for d in per_seed if d is not None]
    if not found:
        return math.nan
    n = sum(d.n_pairs for d in found)
    discordant = sum(d.only_cell + d.only_baseline for d in found)
    return 100 * float(paired_power(n, discordant).mde)


def _of_suite(episodes: pd.DataFrame, suite: str | None) -> pd.DataFrame:
    return episodes if suite is None else episodes[episodes["suite"] == suite]


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
    seeds: dict[str, dict[int, pd.DataFrame]] = {}
    for r in refs:
        if r.seed is not None:
            seeds.setdefault(r.member, {})[r.seed] = episodes[r.label]
    primary = []
    for e in endpoints:
        by_seed = seeds.get(e.member, {}) if e.member not in episodes else {}
        if len(by_seed) > 1:  # a member with training seeds: pooled over them
            row = _pooled_row(e.member, e.cell, e.reference, e.suite, by_seed)
            primary.append(row | {"ran": True})
            continue
        eps = next(iter(by_seed.values())) if by_seed else episodes.get(e.member)
        d = compare(eps, e.cell, e.reference, e.suite) if eps is not None else None
        primary.append(_row(e.member, e.cell, e.reference, e.suite, d) | {"ran": eps is not None})
    for r, p in zip(primary, family_holm(primary), strict=True):
        r["p_holm"] = p
    declared = {(e.member, e.cell, e.reference) for e in endpoints if e.suite is None}
    exploratory = []
    for label, eps in episodes.items():
        ok = eps[eps["error"].isna()]
        reference = agg.reference_cell(set(ok["cell_id"]))
        for d in agg.paired_vs_baseline(eps, baseline=reference) if reference else []:
            if (label, d.cell_id, reference) not in declared:
                exploratory.append(_row(label, d.cell_id, str(reference), None, d))
    for member, by_seed in seeds.items():  # each member with seeds, pooled over them
        if len(by_seed) < 2:
            continue
        first = next(iter(by_seed.values()))
        reference = agg.reference_cell(set(first.loc[first["error"].isna(), "cell_id"]))
        cells = sorted(set().union(*(set(e["cell_id"]) for e in by_seed.values())))
        for cell in cells if reference else []:
            if cell != reference and (member, cell, reference) not in declared:
                exploratory.append(_pooled_row(member, cell, str(reference), None, by_seed))
    return {"primary": primary, "exploratory": exploratory}


def family_holm(primary: Sequence[dict]) -> list[float]:
    """Holm's adjusted p of each declared endpoint over the whole declared family: an endpoint
    not run (or without pairs) counts as p = 1, so the family keeps its declared size and an
    adjusted p given now is never below the one the complete study gives (a rejection now
    stands whatever the missing endpoints show); its own adjusted p is NaN."""
    if not primary:
        return []
    raw = [r["p"] if r["ran"] and np.isfinite(r["p"]) else 1.0 for r in primary]
    adjusted = holm(raw)
    return [
        float(a) if r["ran"] and np.isfinite(r["p"]) else math.nan
        for r, a in zip(primary, adjusted, strict=True)
    ]


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
            "Holm's step-down over these comparisons (family-wise α = 0.05; one not run counts "
            "as p = 1, so the family keeps its declared size). A member with "
            "several training seeds is pooled over them (mean of the seeds' differences, "
            "two-level bootstrap: seeds, then episodes within each task); one seed: McNemar.",
            "",
            "| member | comparison | suite | seeds | Δ success pp (95% CI) | p (test) | Holm p "
            "| pairs | MDE pp |",
            "|---|---|---|---|---|---|---|---|---|",
        ]
        for r in primary:
            pairs = r["n_pairs"] if r["ran"] else "not run"
            lines.append(
                f"| {r['member']} | {r['cell']} vs {r['reference']} | {r['suite'] or 'all'} | "
                f"{r['seeds']}{_per_seed(r)} | {_delta(r)} | {_p(r['p'])} ({r['test']}) | "
                f"{_p(r['p_holm'])} | {pairs} | {_mde(r)} |"
            )
        lines.append("")
    lines += [
        "## Exploratory comparisons",
        "",
        "Not declared before the data: uncorrected p-values, to be read as hypotheses for a "
        "later study, not as findings (so are the sections after this one).",
        "",
        "| member | comparison | seeds | Δ success pp (95% CI) | p, uncorrected (test) | pairs "
        "| MDE pp |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in exploratory:
        lines.append(
            f"| {r['member']} | {r['cell']} vs {r['reference']} | {r['seeds']}{_per_seed(r)} | "
            f"{_delta(r)} | {_p(r['p'])} ({r['test']}) | {r['n_pairs']} | {_mde(r)} |"
        )
    return [*lines, ""]


def _per_seed(r: dict) -> str:
    """Each seed's difference, after the seed count: " (s0 +10.0, s1 -5.0)"."""
    per = r.get("per_seed") or {}
    return " (" + ", ".join(f"s{k} {_pp(v)}" for k, v in per.items()) + ")" if per else ""


def _mde(r: dict) -> str:
    x = r.get("mde_pp", math.nan)
    if x is None or (isinstance(x, float) and math.isnan(x)):
        return "–"
    bound = "≥ " if r.get("seeds", 1) > 1 else ""
    return "none" if not np.isfinite(x) else f"{bound}{x:.1f}"
