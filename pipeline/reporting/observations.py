"""The paper's observations over a study's runs (architecture x environment): STUDY/observations.md,
observations.json and figures.

Sections, each number with an interval:

- the R_img heatmap: architecture x (environment, task), from each run's reference diagnose cell
  (the paper's figure; R_img is the ratio of mean effects, as everywhere in the reports);
- per architecture and environment: R_img with a 95% interval (episodes resampled), E_img and
  E_prop in the environment's action units (the refine space: the backbone's unnormalized
  action output; only R_img compares across environments, as in the paper's X-VLA table);
- IDR's gain per run: success(E) - success(diagnose), paired by episode, with a bootstrap 95%
  interval and the exact McNemar p;
- per member trained with several seeds (one run per training seed): R_img, diagnose's and E's
  success and E's gain pooled over the seeds, two-level bootstrap (pipeline.results.seeds),
  beside each seed's figure;
- R_img against that gain across members: Spearman's rank correlation with an exact permutation
  p (all pairings up to 8 points), one point per member (architecture @ environment), the mean
  over its training seeds;
- R_img over normalized task progress per run (10 bins, ratio of bin means);
- first, the study's declared primary endpoints with Holm's correction and every other paired
  comparison as exploratory (pipeline.reporting.endpoints).
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from pipeline.results import aggregate as agg

if TYPE_CHECKING:
    from pipeline.planning.study import Endpoint

EPS = agg.RIMG_EPS
N_BOOT = 2000
BINS = 10
FIFTHS = 5  # the open-loop reliance's progress labels (pipeline.api.frames.FIFTHS)
OBS_MD = "observations.md"
OBS_JSON = "observations.json"
CONTROL = "@image_blackout"  # the image-zeroed control's perturbation


@dataclass(frozen=True)
class RunRef:
    """One study run as the report sees it."""

    arch: str
    env: str
    run_dir: Path
    seed: int | None = None  # the training seed, where the member lists several

    @property
    def member(self) -> str:
        return f"{self.arch}@{self.env}"

    @property
    def label(self) -> str:
        from pipeline.planning.study import run_label

        return run_label(self.arch, self.env, self.seed)


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


def _diagnose_steps(steps: pd.DataFrame, diag: str) -> pd.DataFrame:
    return steps.loc[
        steps["cell_id"] == diag, ["task_id", "episode_index", "e_img", "e_prop", "progress"]
    ].dropna(subset=["e_img", "e_prop"])


def _run_section(ref: RunRef) -> dict:
    from pipeline.reporting.run_data import load_run, reference_diagnose

    data = load_run(ref.run_dir)
    diag = reference_diagnose(data.steps)
    out: dict = {
        "arch": ref.arch,
        "env": ref.env,
        "seed": ref.seed,
        "label": ref.label,
        "run_dir": str(ref.run_dir),
        "diagnose": diag,
    }
    if diag is None:
        return out
    steps = _diagnose_steps(data.steps, diag)
    per_task = {
        str(t): ratio(g["e_img"].to_numpy(), g["e_prop"].to_numpy())
        for t, g in steps.groupby("task_id")
    }
    steps = without_control(steps)
    out.update(pooled_effects(steps), per_task=per_task)
    binned = np.minimum((steps["progress"].to_numpy() * BINS).astype(int), BINS - 1)
    out["progress"] = [
        ratio(steps["e_img"].to_numpy()[binned == b], steps["e_prop"].to_numpy()[binned == b])
        for b in range(BINS)
    ]
    # the open-loop measure's labels (pipeline.reporting.reliance): fifths, with intervals
    fifth = np.minimum((steps["progress"].to_numpy() * FIFTHS).astype(int), FIFTHS - 1)
    out["progress_fifths"] = []
    for f in range(FIFTHS):
        point, lo, hi = rimg_interval(steps[fifth == f])
        out["progress_fifths"].append(
            {"r_img": point, "ci95": [lo, hi], "steps": int((fifth == f).sum())}
        )
    ok = data.episodes[data.episodes["error"].isna()]
    rates = ok.groupby("cell_id")["success"].agg(["sum", "count"])
    out["success"] = {
        str(c): {
            "n": int(r["count"]),
            "rate": float(r["sum"] / r["count"]),
            "ci95": list(agg.wilson(int(r["sum"]), int(r["count"]))),
        }
        for c, r in rates.iterrows()
    }
    gains = [p for p in agg.paired_vs_baseline(data.episodes, baseline=diag) if p.cell_id == "E"]
    if gains:
        g = gains[0]
        out["gain_E"] = {
            "n_pairs": g.n_pairs,
            "diff": g.diff,
            "ci95": [g.ci_low, g.ci_high],
            "mcnemar_p": g.p_value,
        }
    return out


def _member_section(member: str, refs: list[RunRef]) -> dict:
    """A member's figures pooled over its training seeds (two-level bootstrap)."""
    from pipeline.reporting.run_data import load_run, reference_diagnose
    from pipeline.results.seeds import pooled_paired, pooled_rimg, pooled_success

    data = {r.seed: load_run(r.run_dir) for r in refs}
    diag = {s: reference_diagnose(d.steps) for s, d in data.items()}
    out: dict = {"member": member, "seeds": sorted(data)}
    if any(v is None for v in diag.values()) or len(set(diag.values())) != 1:
        return out  # seeds without one common diagnose cell: nothing to pool
    cell = next(iter(diag.values()))
    steps = {s: without_control(_diagnose_steps(d.steps, cell)) for s, d in data.items()}
    episodes = {s: d.episodes for s, d in data.items()}
    out["diagnose"] = cell
    out["r_img"] = pooled_rimg(steps).record()
    out["success"] = {c: pooled_success(episodes, c).record() for c in (cell, "E")}
    if all((e["cell_id"] == "E").any() for e in episodes.values()):
        out["gain_E"] = pooled_paired(episodes, "E", cell).record()
    return out


def _points(runs: list[dict]) -> list[dict]:
    """One point per member for the correlation: R_img and E's gain, each the mean over the
    member's training seeds (a run without a seed is a member of one)."""
    by_member: dict[str, list[dict]] = {}
    for r in runs:
        if "r_img" in r and "gain_E" in r:
            by_member.setdefault(f"{r['arch']}@{r['env']}", []).append(r)
    return [
        {
            "member": m,
            "seeds": len(rs),
            "r_img": float(np.mean([r["r_img"] for r in rs])),
            "gain": float(np.mean([r["gain_E"]["diff"] for r in rs])),
        }
        for m, rs in by_member.items()
    ]


def build(refs: list[RunRef]) -> dict:
    runs = [_run_section(r) for r in refs]
    grouped: dict[str, list[RunRef]] = {}
    for r in refs:
        grouped.setdefault(r.member, []).append(r)
    members = [_member_section(m, rs) for m, rs in grouped.items() if len(rs) > 1]
    points = _points(runs)
    corr = rank_correlation([p["r_img"] for p in points], [p["gain"] for p in points])
    corr["members"] = [p["member"] for p in points]
    corr["seeds"] = {p["member"]: p["seeds"] for p in points}
    return {"runs": runs, "members": members, "rimg_vs_gain": corr}


def _pct(x: float) -> str:
    return "–" if x is None or not np.isfinite(x) else f"{100 * x:.1f}"


def markdown(result: dict, name: str) -> str:
    from pipeline.reporting.endpoints import markdown as comparisons_markdown

    runs = [r for r in result["runs"] if "r_img" in r]
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
    lines += [
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
    lines += [
        "",
        "Pooled over each environment's tasks and perturbations, without the image-zeroed "
        "control (black images: E_img is ~0 by construction; it shows in the heatmap). "
        "E_img and E_prop are L2 norms in each environment's action units (the backbone's "
        "unnormalized output, where IDR refines): compare them within an environment only.",
        "",
        "![R_img heatmap](figures/observations_rimg_heatmap.png)",
        "",
        *_members_markdown(result.get("members") or []),
        "## IDR mode E against diagnose, per run (exploratory unless a primary endpoint)",
        "",
        "| arch | env | Δ success pp (95% CI) | McNemar p | pairs |",
        "|---|---|---|---|---|",
    ]
    for r in result["runs"]:
        g = r.get("gain_E")
        if g is None:
            continue
        lines.append(
            f"| {r.get('label') or r['arch']} | {r['env']} | {100 * g['diff']:+.1f} [{100 * g['ci95'][0]:+.1f}, "
            f"{100 * g['ci95'][1]:+.1f}] | {g['mcnemar_p']:.3g} | {g['n_pairs']} |"
        )
    c = result["rimg_vs_gain"]
    rho = "–" if not np.isfinite(c["rho"]) else f"{c['rho']:+.2f}"
    p = "–" if not np.isfinite(c["p"]) else f"{c['p']:.3g}"
    lines += [
        "",
        "## R_img against IDR's gain across members (exploratory)",
        "",
        f"Spearman ρ = {rho} over {c['n']} members, one point per architecture @ environment "
        f"(the mean over its training seeds: {_seed_counts(c)}), permutation p = {p}: "
        f"**{c['finding']}**.",
        "",
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
    lines += ["", "![R_img over progress](figures/observations_rimg_progress.png)", ""]
    return "\n".join(lines)


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


def heatmap_matrix(result: dict) -> pd.DataFrame:
    rows = {}
    for r in result["runs"]:
        for task, v in (r.get("per_task") or {}).items():
            row = r["arch"] if r.get("seed") is None else f"{r['arch']}:seed{r['seed']}"
            rows.setdefault(row, {})[f"{r['env']}\n{task}"] = v
    return pd.DataFrame(rows).T.sort_index().sort_index(axis=1)


def write(
    study_dir: Path, refs: list[RunRef], name: str, endpoints: Sequence[Endpoint] = ()
) -> dict:
    """Build the observations from the runs and write STUDY/observations.{md,json} and figures;
    ``endpoints``: the study's declared primary comparisons (pipeline.planning.study), given
    with Holm's correction, every other comparison labelled exploratory."""
    from pipeline.planning.study import ENDPOINTS_FILE
    from pipeline.reporting.endpoints import comparisons
    from pipeline.reporting.figures import _figure, rimg_heatmap, save
    from pipeline.rundir import FIGURES_DIR

    result = build(refs)
    result["name"] = name
    result["comparisons"] = comparisons(refs, endpoints)
    pinned = study_dir / ENDPOINTS_FILE
    result["endpoints_hash"] = json.loads(pinned.read_text())["hash"] if pinned.is_file() else None
    study_dir.mkdir(parents=True, exist_ok=True)
    (study_dir / OBS_JSON).write_text(json.dumps(result, indent=2, default=float) + "\n")
    figs = study_dir / FIGURES_DIR
    matrix = heatmap_matrix(result)
    if not matrix.empty:
        fig = rimg_heatmap(matrix, "Baseline R_img per architecture x (environment, task)")
        fig.axes[0].set_xlabel("environment / task")
        fig.axes[0].set_ylabel("architecture")
        save(fig, figs / "observations_rimg_heatmap.png")
    fig = _figure()
    ax = fig.add_subplot()
    x = (np.arange(BINS) + 0.5) / BINS
    for r in result["runs"]:
        if "progress" in r:
            ax.plot(
                x,
                r["progress"],
                marker="o",
                ms=3,
                label=r.get("label") or f"{r['arch']}@{r['env']}",
            )
    ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="normalized task progress", ylabel="R_img")
    ax.set_title("R_img over task progress (diagnose cells)")
    if ax.get_legend_handles_labels()[0]:  # no run with a diagnose cell: no lines to name
        ax.legend(fontsize=8)
    save(fig, figs / "observations_rimg_progress.png")
    (study_dir / OBS_MD).write_text(markdown(result, name))
    return result
