"""Open-loop reliance, its figures and report: every member of a benchmark measured on one shared
set of held-out demonstration frames (``pipeline.api.reliance`` measures, ``pipeline.api.frames``
reads the frames), so observations 2 and 3 are read without
closed-loop success as a confound (each member sees the same frames, none of its own making).

Per member: E_img, E_prop and R_img (the ratio of mean effects, as everywhere) over all frames,
by fifth of episode progress and by gripper phase, each R_img with a 95% interval that
resamples whole episodes (frames of one episode are not independent:
``observation_stats.rimg_interval``). For one member, R_img under each intervention strategy
(``zero``, ``mean``, ``gaussian``, for do(V) and do(S) alike): how much the figure owes to the
choice of counterfactual. Writes ``OUT/reliance.json``, ``reliance.md``, the per-frame table
``reliance_frames.parquet`` and a figure of R_img over progress.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from idr_core.interventions import InterventionConfig

from pipeline.results.observation_stats import rimg_interval

RELIANCE_JSON = "reliance.json"
RELIANCE_MD = "reliance.md"
FRAMES_TABLE = "reliance_frames.parquet"
FIFTHS = 5  # progress through an episode, in fifths (pipeline.api.frames labels each frame)
PHASES = ("open", "closed", "released")  # gripper phases (pipeline.api.frames)
MIN_FRAMES = 2000  # what a finding needs; fewer are reported with a warning line


def rimg_figure(rows: pd.DataFrame) -> dict[str, Any]:
    point, lo, hi = rimg_interval(rows)
    return {
        "r_img": point,
        "ci95": [lo, hi],
        "frames": len(rows),
        "episodes": int(rows.groupby(["task_id", "episode_index"]).ngroups) if len(rows) else 0,
    }


def summarize(rows: pd.DataFrame) -> dict[str, Any]:
    """One member's figures on the frames (``rows``: ``measure``'s table)."""
    out = rimg_figure(rows)
    out["e_img"] = float(rows["e_img"].mean())
    out["e_prop"] = float(rows["e_prop"].mean())
    out["by_fifth"] = [rimg_figure(rows[rows["fifth"] == f]) for f in range(FIFTHS)]
    out["by_phase"] = {p: rimg_figure(rows[rows["phase"] == p]) for p in PHASES}
    out["no_gripper_frames"] = int((rows["phase"] == "none").sum())
    return out


def intervention_record(iv: InterventionConfig) -> dict[str, Any]:
    return {
        "strategy": iv.strategy,
        "image_space": iv.image_space,
        "state_space": iv.state_space,
        "noise_scale": iv.noise_scale,
    }


def _pct(x: float) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{100 * x:.1f}"


def _cell(fig: dict[str, Any]) -> str:
    if not fig["frames"]:
        return "–"
    lo, hi = fig["ci95"]
    return f"{_pct(fig['r_img'])} [{_pct(lo)}, {_pct(hi)}]"


def markdown(result: dict[str, Any]) -> str:
    frames = result["frames"]
    iv = result["intervention"]
    lines = [
        "# Open-loop reliance on shared held-out frames",
        "",
        f"{frames['n']} frames of {frames['episodes']} held-out demonstration episodes "
        f"(`{frames['source']}`), the same for every member; do(V) and do(S) `{iv['strategy']}` "
        f"(do(S) {iv['state_space']}). R_img % with a 95% interval resampling episodes.",
        "",
    ]
    if frames["n"] < MIN_FRAMES:
        lines += [
            f"**{frames['n']} frames: fewer than the {MIN_FRAMES} a finding needs** (a check "
            "of the pipeline, not a measurement).",
            "",
        ]
    lines += [
        "## Per member",
        "",
        "| member | R_img % (95% CI) | E_img | E_prop | frames | episodes |",
        "|---|---|---|---|---|---|",
    ]
    for name, m in result["members"].items():
        lines.append(
            f"| {name} | {_cell(m)} | {m['e_img']:.3g} | {m['e_prop']:.3g} | {m['frames']} | "
            f"{m['episodes']} |"
        )
    lines += [
        "",
        "## By progress through the episode (fifths)",
        "",
        "| member | "
        + " | ".join(f"{f / FIFTHS:.1f}-{(f + 1) / FIFTHS:.1f}" for f in range(FIFTHS))
        + " |",
        "|---|" + "---|" * FIFTHS,
    ]
    for name, m in result["members"].items():
        lines.append(f"| {name} | " + " | ".join(_cell(f) for f in m["by_fifth"]) + " |")
    lines += [
        "",
        "## By gripper phase (from the demonstration's gripper command)",
        "",
        "| member | " + " | ".join(PHASES) + " | frames without a grasp |",
        "|---|" + "---|" * (len(PHASES) + 1),
    ]
    for name, m in result["members"].items():
        lines.append(
            f"| {name} | "
            + " | ".join(
                f"{_cell(m['by_phase'][p])} (n={m['by_phase'][p]['frames']})" for p in PHASES
            )
            + f" | {m['no_gripper_frames']} |"
        )
    if "strategies" in result:
        s = result["strategies"]
        lines += [
            "",
            f"## The counterfactual's strategy: {s['member']}",
            "",
            "| strategy (do(V) and do(S)) | R_img % (95% CI) |",
            "|---|---|",
        ]
        lines += [f"| {k} | {_cell(v)} |" for k, v in s["by_strategy"].items()]
    lines += ["", "![R_img over progress](figures/reliance_progress.png)", ""]
    return "\n".join(lines)


def write(out: Path, result: dict[str, Any], table: pd.DataFrame) -> None:
    from pipeline.reporting.figures import _figure, save
    from pipeline.rundir import FIGURES_DIR

    out.mkdir(parents=True, exist_ok=True)
    (out / RELIANCE_JSON).write_text(json.dumps(result, indent=2, default=float) + "\n")
    table.to_parquet(out / FRAMES_TABLE, index=False)
    fig = _figure()
    ax = fig.add_subplot()
    x = (np.arange(FIFTHS) + 0.5) / FIFTHS
    for name, m in result["members"].items():
        y = [f["r_img"] for f in m["by_fifth"]]
        lo = [f["ci95"][0] for f in m["by_fifth"]]
        hi = [f["ci95"][1] for f in m["by_fifth"]]
        ax.plot(x, y, marker="o", ms=3, label=name)
        ax.fill_between(x, lo, hi, alpha=0.15)
    ax.set(xlim=(0, 1), ylim=(0, 1), xlabel="progress through the episode", ylabel="R_img")
    ax.set_title("Open-loop R_img on held-out frames (95% CI, episodes resampled)")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=8)
    save(fig, out / FIGURES_DIR / "reliance_progress.png")
    (out / RELIANCE_MD).write_text(markdown(result))
