"""STUDY/observations.md from the observations' figures (``pipeline.reporting.observations``):
the primary endpoints, R_img per architecture and environment, members over their training
seeds, IDR's gain per run, R_img against that gain, and R_img over task progress."""

from __future__ import annotations

import math

import numpy as np

from pipeline.results.observation_stats import BINS, FIFTHS


def _pct(x: float) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{100 * x:.1f}"


def markdown(result: dict, name: str) -> str:
    """STUDY/observations.md: its sections in order, each from ``result`` (``build``'s)."""
    runs = [r for r in result["runs"] if "r_img" in r]
    lines = [
        *_header_markdown(result, name),
        *_rimg_markdown(runs),
        *_members_markdown(result.get("members") or []),
        *_gains_markdown(result["runs"]),
        *_correlation_markdown(result["rimg_vs_gain"]),
        *_progress_markdown(runs),
    ]
    return "\n".join(lines)


def _header_markdown(result: dict, name: str) -> list[str]:
    """The title, what each number is taken from, and the study's endpoints where declared."""
    from pipeline.reporting.endpoints import markdown as comparisons_markdown

    lines = [f"# The paper's observations: `{name}`", ""]
    seeded = [r for r in result["runs"] if r.get("seed") is not None]
    lines += [
        f"{len(result['runs'])} runs (architecture @ environment"
        f"{', one per training seed where a member lists seeds' if seeded else ''}); each "
        "number from its run's diagnose cell (R_img) or its E and diagnose cells paired by "
        "episode (gain).",
        "",
    ]
    if "comparisons" in result:
        lines += comparisons_markdown(result["comparisons"], result.get("endpoints_hash"))
    return lines


def _rimg_markdown(runs: list[dict]) -> list[str]:
    """R_img per architecture and environment, and the heatmap."""
    lines = [
        "## R_img per architecture and environment (observations 1 and 2)",
        "",
        "| arch | env | seed | R_img % (95% CI) | E_img | E_prop | inferences "
        "| success diagnose % (95% CI) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in runs:
        s = r["success"].get(r["diagnose"], {})
        ci = s.get("ci95", [math.nan, math.nan])
        seed = "–" if r.get("seed") is None else r["seed"]
        lines.append(
            f"| {r['arch']} | {r['env']} | {seed} | {_pct(r['r_img'])} [{_pct(r['r_img_ci95'][0])}, "
            f"{_pct(r['r_img_ci95'][1])}] | {r['e_img']:.3g} | {r['e_prop']:.3g} | "
            f"{r['inferences']} | {_pct(s.get('rate', math.nan))} [{_pct(ci[0])}, {_pct(ci[1])}] |"
        )
    return [
        *lines,
        "",
        "Pooled over each environment's tasks and perturbations, without the image-zeroed "
        "control (black images: E_img is ~0 by construction; it shows in the heatmap). "
        "E_img and E_prop are L2 norms in each environment's action units (the backbone's "
        "unnormalized output, where IDR refines): compare them within an environment only.",
        "",
        "![R_img heatmap](figures/observations_rimg_heatmap.png)",
        "",
    ]


def _gains_markdown(all_runs: list[dict]) -> list[str]:
    """IDR's gain (mode E against diagnose, paired by episode) per run that has both cells."""
    lines = [
        "## IDR mode E against diagnose, per run (exploratory unless a primary endpoint)",
        "",
        "| arch | env | Δ success pp (95% CI) | McNemar p | pairs |",
        "|---|---|---|---|---|",
    ]
    for r in all_runs:
        g = r.get("gain_E")
        if g is None:
            continue
        lines.append(
            f"| {r.get('label') or r['arch']} | {r['env']} | {100 * g['diff']:+.1f} [{100 * g['ci95'][0]:+.1f}, "
            f"{100 * g['ci95'][1]:+.1f}] | {g['mcnemar_p']:.3g} | {g['n_pairs']} |"
        )
    return lines


def _correlation_markdown(c: dict) -> list[str]:
    """R_img against IDR's gain across members: Spearman's rho and its permutation p."""
    rho = "–" if not np.isfinite(c["rho"]) else f"{c['rho']:+.2f}"
    p = "–" if not np.isfinite(c["p"]) else f"{c['p']:.3g}"
    return [
        "",
        "## R_img against IDR's gain across members (exploratory)",
        "",
        f"Spearman ρ = {rho} over {c['n']} members, one point per architecture @ environment "
        f"(the mean over its training seeds: {_seed_counts(c)}), permutation p = {p}: "
        f"**{c['finding']}**.",
        "",
    ]


def _progress_markdown(runs: list[dict]) -> list[str]:
    """R_img over task progress per run: in BINS bins, then by fifths with intervals."""
    lines = [
        "## R_img over task progress (observation 3)",
        "",
        "| run | " + " | ".join(f"{b / BINS:.1f}-{(b + 1) / BINS:.1f}" for b in range(BINS)) + " |",
        "|---|" + "---|" * BINS,
    ]
    for r in runs:
        lines.append(
            f"| {r.get('label') or r['arch'] + '@' + r['env']} | "
            + " | ".join(_pct(v) for v in r["progress"])
            + " |"
        )
    lines += [
        "",
        "By fifths of progress, with 95% intervals (episodes resampled), as the open-loop "
        "measure on held-out frames labels them (`idr-eval reliance`):",
        "",
        "| run | "
        + " | ".join(f"{f / FIFTHS:.1f}-{(f + 1) / FIFTHS:.1f}" for f in range(FIFTHS))
        + " |",
        "|---|" + "---|" * FIFTHS,
    ]
    for r in runs:
        cells = [
            "–"
            if not np.isfinite(f["r_img"])
            else f"{_pct(f['r_img'])} [{_pct(f['ci95'][0])}, {_pct(f['ci95'][1])}]"
            for f in r.get("progress_fifths") or []
        ]
        lines.append(
            f"| {r.get('label') or r['arch'] + '@' + r['env']} | " + " | ".join(cells) + " |"
        )
    return [*lines, "", "![R_img over progress](figures/observations_rimg_progress.png)", ""]


def _seed_counts(c: dict) -> str:
    seeds = c.get("seeds") or {}
    return ", ".join(f"{m} {k}" for m, k in seeds.items()) or "none"


def _interval(rec: dict, scale: float = 100, signed: bool = False) -> str:
    fmt = "+.1f" if signed else ".1f"
    v, (lo, hi) = rec["value"], rec["ci95"]
    if not np.isfinite(v):
        return "–"
    return f"{scale * v:{fmt}} [{scale * lo:{fmt}}, {scale * hi:{fmt}}]"


def _members_markdown(members: list[dict]) -> list[str]:
    """Members trained with several seeds: their figures pooled over the seeds."""
    rows = [m for m in members if "r_img" in m]
    if not rows:
        return []
    lines = [
        "## Members over their training seeds (seeds as a random effect)",
        "",
        "Each figure is the mean of the seeds' figures; its 95% interval resamples training "
        "seeds, then episodes within each task of each drawn seed (two-level bootstrap), so it "
        "speaks for another seed of the same recipe, which an interval over one seed's episodes "
        "does not. Per seed in parentheses.",
        "",
        "| member | seeds | R_img % | success diagnose % | success E % | E − diagnose pp | "
        "p (bootstrap) |",
        "|---|---|---|---|---|---|---|",
    ]
    for m in rows:
        diag, e = m["success"].get(m["diagnose"]), m["success"].get("E")
        gain = m.get("gain_E")

        def per(rec: dict | None, signed: bool = False) -> str:
            if not rec:
                return "–"
            seeds = ", ".join(
                f"s{k} {100 * v:{'+.1f' if signed else '.1f'}}" for k, v in rec["per_seed"].items()
            )
            return f"{_interval(rec, signed=signed)} ({seeds})"

        lines.append(
            f"| {m['member']} | {len(m['seeds'])} | {per(m['r_img'])} | {per(diag)} | {per(e)} "
            f"| {per(gain, signed=True)} | {_pct_p(gain)} |"
        )
    return [*lines, ""]


def _pct_p(gain: dict | None) -> str:
    return "–" if not gain or not np.isfinite(gain["p"]) else f"{gain['p']:.3g}"
