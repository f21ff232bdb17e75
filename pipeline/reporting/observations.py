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

The estimators: ``pipeline.results.observation_stats``; the page:
``pipeline.reporting.observations_markdown``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from pipeline.reporting.observations_markdown import markdown
from pipeline.results import aggregate as agg
from pipeline.results.observation_stats import (
    BINS,
    FIFTHS,
    pooled_effects,
    rank_correlation,
    ratio,
    rimg_interval,
    without_control,
)

if TYPE_CHECKING:
    from pipeline.planning.study import Endpoint

OBS_MD = "observations.md"
OBS_JSON = "observations.json"


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
    return {"runs": runs, "members": members, "rimg_vs_gain": rimg_vs_gain(runs)}


def rimg_vs_gain(runs: list[dict]) -> dict:
    """R_img against E's gain across members (one point per member, its seeds' mean)."""
    points = _points(runs)
    corr = rank_correlation([p["r_img"] for p in points], [p["gain"] for p in points])
    corr["members"] = [p["member"] for p in points]
    corr["seeds"] = {p["member"]: p["seeds"] for p in points}
    return corr


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
