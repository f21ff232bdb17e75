"""The paper's analysis figures, as PNGs, from a run's Parquet tables (no live objects).

- ``rimg_heatmap``: R_img per backbone x suite (the paper's Fig. of visual importance patterns),
  R_img = mean E_img / (mean E_img + mean E_prop + eps) over the inferences of the diagnose
  cell (it executes the base action, so it measures the baseline's effects);
- ``rimg_progress``: R_img over normalized task progress (control step / episode length) for
  the baseline (the diagnose cell), mode E and mode F, with the gripper's close and open events
  as dashed lines (sign changes of the gripper action; its median progress over episodes);
- ``success_alpha`` / ``success_tau``: success rate vs alpha and vs tau with Wilson 95%
  intervals, the baseline as a band;
- ``gate_progress``: how often the gate is open over normalized progress, per refining cell.

Builders take data frames and return a matplotlib ``Figure`` (tests inspect its axes before
saving); ``write_figures`` reads a run directory and saves them to ``RUN_DIR/figures/``. Only
the object-oriented API with the Agg canvas is used: importing this module never changes the
pyplot backend of a notebook.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from pipeline.reporting.run_data import (
    RunData,
    gripper_events,
    load_run,
    reference_diagnose,
    rimg_matrix,
)
from pipeline.results import aggregate as agg
from pipeline.rundir import FIGURES_DIR, write_atomic

REFINING = ("A", "B", "C", "D", "E", "F")
MAX_SERIES = 10


def _figure(width: float = 6.4, height: float = 4.0) -> Figure:
    fig = Figure(figsize=(width, height), dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


# -- data -----------------------------------------------------------------------------------------


def binned(
    df: pd.DataFrame, column: str, bins: int = 10, cells: list[str] | None = None
) -> pd.DataFrame:
    """Mean of ``column`` per cell (of ``cells``; None: all) and progress bin, with a normal
    95% half-width. Reads three columns of ``df`` (millions of rows: nothing else copied)."""
    keep = df[column].notna()
    if cells is not None:
        keep &= df["cell_id"].isin(cells)
    df = df.loc[keep, ["cell_id", "progress", column]]
    df["bin"] = np.minimum((df["progress"] * bins).astype(int), bins - 1)
    g = df.groupby(["cell_id", "bin"])[column]
    out = g.agg(["mean", "std", "count"]).reset_index()
    out["half"] = 1.96 * out["std"].fillna(0.0) / np.sqrt(out["count"].clip(lower=1))
    out["x"] = (out["bin"] + 0.5) / bins
    return out


def pick_cell(
    cells: pd.DataFrame,
    mode: str,
    strategy: str | None,
    tau_labels: dict[str, str],
    alpha: float,
) -> str | None:
    """The cell that stands for ``mode`` (``cells``: cell_id, mode, strategy, alpha per cell):
    the one named after it, else the best match to the reference's intervention, the config's
    declared ``alpha`` (``RunData.reference_alpha``) and the paper's tau rule (``calibrated``),
    in that order of weight."""
    of_mode = cells[cells["mode"] == mode].sort_values("cell_id")
    if of_mode.empty:
        return None
    if mode in set(of_mode["cell_id"]):
        return mode
    score = (
        4 * (of_mode["strategy"] == strategy).astype(int)
        + 2 * np.isclose(of_mode["alpha"].astype(float), alpha).astype(int)
        + of_mode["cell_id"].map(lambda c: tau_labels.get(c) == "calibrated").astype(int)
    )
    return str(of_mode.loc[score.idxmax(), "cell_id"])


# -- builders ---------------------------------------------------------------------------------------


def rimg_heatmap(matrix: pd.DataFrame, title: str = "") -> Figure:
    """Heatmap of an ``rimg_matrix`` (rows backbones, columns suites), values written in."""
    fig = _figure(max(4.8, 1.8 + 1.3 * matrix.shape[1]), max(3.2, 1.6 + 0.6 * matrix.shape[0]))
    ax = fig.add_subplot()
    values = matrix.to_numpy(dtype=float)
    im = ax.imshow(values, cmap="viridis", vmin=0.0, vmax=1.0, aspect="auto")
    ax.set_xticks(range(matrix.shape[1]), [str(c) for c in matrix.columns], rotation=20)
    ax.set_yticks(range(matrix.shape[0]), [str(r) for r in matrix.index])
    for (i, j), v in np.ndenumerate(values):
        if np.isfinite(v):
            ax.text(
                j, i, f"{100 * v:.1f}%", ha="center", va="center", color="w" if v < 0.6 else "k"
            )
    ax.set_xlabel("suite")
    ax.set_ylabel("backbone")
    ax.set_title(title or "Baseline R_img = E_img / (E_img + E_prop)", fontsize=10)
    fig.colorbar(im, ax=ax, label="R_img")
    return fig


def rimg_progress(
    prog: pd.DataFrame,
    cells: list[tuple[str, str]],
    events: dict[str, list[float]],
    bins: int = 10,
) -> Figure:
    """R_img over normalized progress, one line per (cell_id, label), gripper events dashed.

    Per bin the mean of the per-inference R_img with a normal 95% band (the phase plot; the
    heatmap's one number per suite is the ratio of mean effects instead)."""
    fig = _figure()
    ax = fig.add_subplot()
    b = binned(prog, "r_img", bins, [c for c, _ in cells])
    for cell, label in cells:
        s = b[b["cell_id"] == cell]
        if s.empty:
            continue
        (line,) = ax.plot(s["x"], s["mean"], marker="o", ms=3, label=label)
        ax.fill_between(
            s["x"], s["mean"] - s["half"], s["mean"] + s["half"], color=line.get_color(), alpha=0.15
        )
    for kind, color in (("close", "tab:red"), ("open", "tab:green")):
        for k, x in enumerate(events.get(kind, [])):
            ax.axvline(x, ls="--", lw=1, color=color, label=f"gripper {kind}" if k == 0 else None)
    ax.set_xlim(0, 1)
    ax.set_xlabel("normalized task progress (step / episode length)")
    ax.set_ylabel("R_img")
    ax.set_title("Visual importance over task progress")
    ax.legend(fontsize=8, loc="best")
    return fig


def gate_progress(prog: pd.DataFrame, cells: list[str], bins: int = 10) -> Figure:
    """Share of inferences with the gate open, over normalized progress, one line per cell."""
    fig = _figure()
    ax = fig.add_subplot()
    b = binned(prog, "gate", bins, cells)
    for cell in cells:
        s = b[b["cell_id"] == cell]
        if not s.empty:
            ax.plot(s["x"], s["mean"], marker="o", ms=3, label=cell)
    ax.set_xlim(0, 1)
    ax.set_ylim(-0.03, 1.03)
    ax.set_xlabel("normalized task progress (step / episode length)")
    ax.set_ylabel("gate activation rate")
    ax.set_title("How often IDR refines, over task progress")
    ax.legend(fontsize=8, loc="best")
    return fig


def sweep_table(
    episodes: pd.DataFrame, param: str, tau_labels: dict[str, str] | None = None
) -> pd.DataFrame:
    """Per refining cell: the swept value (``x``, its tick label), its series, success with a
    Wilson 95% interval. A series is a set of cells equal in every parameter but ``param``;
    only series with two or more values of it are kept."""
    tau_labels = tau_labels or {}
    df = episodes[episodes["error"].isna() & episodes["mode"].isin(REFINING)]
    if df.empty:
        return pd.DataFrame()
    rows = []
    for cell, g in df.groupby("cell_id"):
        r = g.iloc[0]
        tau = float(g["tau"].mean())
        tau_key = tau_labels.get(str(cell), f"{tau:g}")
        values = {"alpha": float(r["alpha"]), "tau": tau}
        labels = {
            "alpha": f"{r['alpha']:g}",
            "tau": f"{tau_labels[cell]}\n({tau:.3g})" if cell in tau_labels else _tau_text(tau),
        }
        others = {
            "mode": r["mode"],
            "guidance": r["guidance"],
            "strategy": r["strategy"],
            "alpha": f"{r['alpha']:g}",
            "beta": f"{r['beta']:g}",
            "lam": f"{r['lam']:g}",
            "tau": tau_key,
        }
        others.pop(param)
        k, n = int(g["success"].sum()), len(g)
        lo, hi = agg.wilson(k, n)
        rows.append(
            {
                "cell_id": cell,
                "x": values[param],
                "label": labels[param],
                "series": ", ".join(f"{k_}={v}" for k_, v in others.items()),
                "mode": r["mode"],
                "success": k / n,
                "ci_low": lo,
                "ci_high": hi,
                "n": n,
            }
        )
    out = pd.DataFrame(rows)
    keep = out.groupby("series")["label"].transform("nunique") >= 2
    return out[keep].sort_values(["series", "x"]).reset_index(drop=True)


def _tau_text(tau: float) -> str:
    return "inf" if math.isinf(tau) else f"{tau:g}"


def _short_series(series: list[str]) -> dict[str, str]:
    """Legend labels: only the parameters that differ between the series (else the mode)."""
    parts = [dict(p.split("=", 1) for p in s.split(", ")) for s in series]
    differ = [k for k in parts[0] if len({p.get(k) for p in parts}) > 1]
    if not differ:
        return {s: f"mode {p['mode']}" for s, p in zip(series, parts, strict=True)}
    return {
        s: ", ".join(f"mode {p[k]}" if k == "mode" else f"{k}={p[k]}" for k in differ)
        for s, p in zip(series, parts, strict=True)
    }


def success_sweep(
    table: pd.DataFrame, param: str, baseline: tuple[str, float, float, float] | None = None
) -> Figure:
    """Success (%) vs the swept parameter on a categorical axis (alpha 0.02 ... 1, tau ... 999),
    one line with Wilson 95% error bars per series; the baseline as a line and band."""
    fig = _figure()
    ax = fig.add_subplot()
    ticks = table.drop_duplicates("label").sort_values("x")
    pos = {label: i for i, label in enumerate(ticks["label"])}
    series = list(dict.fromkeys(table["series"]))[:MAX_SERIES]
    names = _short_series(series)
    for s in series:
        t = table[table["series"] == s].sort_values("x")
        xs = [pos[label] for label in t["label"]]
        y = 100 * t["success"].to_numpy()
        err = 100 * np.vstack([t["success"] - t["ci_low"], t["ci_high"] - t["success"]])
        # Wilson's bound at 0% or 100% lies a rounding error inside the rate: never negative
        err = np.clip(err, 0.0, None)
        ax.errorbar(xs, y, yerr=err, marker="o", capsize=3, label=names[s])
    if baseline is not None:
        name, rate, lo, hi = baseline
        ax.axhline(100 * rate, color="k", ls=":", lw=1.2, label=f"{name} (95% CI)")
        ax.axhspan(100 * lo, 100 * hi, color="k", alpha=0.08)
    ax.set_xticks(list(pos.values()), list(pos.keys()), fontsize=8)
    symbol = {"alpha": "correction scale α", "tau": "intervention threshold τ"}.get(param, param)
    ax.set_xlabel(symbol)
    ax.set_ylabel("success rate (%)")
    ax.set_ylim(-3, 103)
    ax.set_title(f"Success vs {param} (Wilson 95% intervals)")
    ax.legend(fontsize=8, loc="best")
    return fig


# -- a run directory ------------------------------------------------------------------------------


@dataclass
class Figures:
    """Figures of one run: built (name -> Figure) and skipped (name -> why)."""

    built: dict[str, Figure]
    skipped: dict[str, str]


CAPTIONS = {
    "rimg_heatmap": "R_img (visual importance of the baseline) per backbone x suite",
    "rimg_progress": "R_img over normalized task progress: baseline, E and F; gripper events dashed",
    "success_alpha": "Success vs alpha, Wilson 95% intervals",
    "success_tau": "Success vs tau, Wilson 95% intervals",
    "gate_progress": "Gate activation rate over normalized task progress",
}


def _reference_success(episodes: pd.DataFrame) -> tuple[str, float, float, float] | None:
    ok = episodes[episodes["error"].isna()]
    ref = agg.reference_cell(set(ok["cell_id"]))
    if ref is None:
        return None
    g = ok[ok["cell_id"] == ref]
    lo, hi = agg.wilson(int(g["success"].sum()), len(g))
    return ref, float(g["success"].mean()), lo, hi


def build_figures(data: RunData, bins: int = 10) -> Figures:
    """Every figure the run's cells allow; a figure the grid cannot feed is skipped with why."""
    built: dict[str, Figure] = {}
    skipped: dict[str, str] = {}
    eps, prog = data.episodes, data.steps
    ok = eps[eps["error"].isna()]
    if ok.empty:
        return Figures({}, dict.fromkeys(CAPTIONS, "no episodes without error"))
    per_cell = ok.groupby("cell_id")[["mode", "strategy", "alpha"]].first().reset_index()
    modes = dict(zip(per_cell["cell_id"], per_cell["mode"], strict=True))
    ref = reference_diagnose(per_cell)
    if ref is None:
        why = "needs a diagnose cell (mode diagnose measures the baseline's effects)"
        skipped["rimg_heatmap"] = skipped["rimg_progress"] = why
    else:
        ref_steps = prog[prog["cell_id"] == ref]
        built["rimg_heatmap"] = rimg_heatmap(rimg_matrix(ref_steps))
        lines = [(ref, f"baseline ({ref}: executes a_base)")]
        strategy = str(per_cell.set_index("cell_id").loc[ref, "strategy"])
        for mode in ("E", "F"):
            cell = pick_cell(per_cell, mode, strategy, data.tau_labels, data.reference_alpha)
            if cell is not None:
                lines.append((cell, f"mode {mode} ({cell})" if cell != mode else f"mode {mode}"))
        built["rimg_progress"] = rimg_progress(prog, lines, gripper_events(ref_steps), bins)
    baseline = _reference_success(eps)
    for param in ("alpha", "tau"):
        table = sweep_table(eps, param, data.tau_labels)
        if table.empty:
            skipped[f"success_{param}"] = f"no refining cells that differ only in {param}"
        else:
            built[f"success_{param}"] = success_sweep(table, param, baseline)
    refining = sorted(c for c, m in modes.items() if m in REFINING)[:MAX_SERIES]
    if refining:
        built["gate_progress"] = gate_progress(prog, refining, bins)
    else:
        skipped["gate_progress"] = "no refining cells (modes A-F)"
    return Figures(built, skipped)


def cell_figures(data: RunData, cell: str, bins: int = 10) -> Figures:
    """One cell's figures (its MLflow child run's): R_img over progress, the cell against the
    run's reference diagnose cell, and the cell's gate rate over progress if it refines."""
    built: dict[str, Figure] = {}
    skipped: dict[str, str] = {}
    ok = data.episodes[data.episodes["error"].isna()]
    per_cell = ok.groupby("cell_id")[["mode", "strategy", "alpha"]].first()
    if cell not in per_cell.index:
        return Figures({}, {"rimg_progress": "no episodes without error"})
    mode = str(per_cell.loc[cell, "mode"])
    if mode == "baseline":
        skipped["rimg_progress"] = "a baseline cell runs no counterfactual passes"
    else:
        ref = reference_diagnose(per_cell.reset_index())
        lines = [(cell, cell)]
        if ref is not None and ref != cell:
            lines.insert(0, (ref, f"baseline ({ref}: executes a_base)"))
        ref_steps = data.steps[data.steps["cell_id"] == (ref or cell)]
        built["rimg_progress"] = rimg_progress(data.steps, lines, gripper_events(ref_steps), bins)
    if mode in REFINING:
        built["gate_progress"] = gate_progress(data.steps, [cell], bins)
    return Figures(built, skipped)


def progress_curves(data: RunData, bins: int = 10) -> dict[str, dict[str, list[tuple[int, float]]]]:
    """Per cell: the mean R_img (and for a refining cell the gate rate) per progress bin as
    (step, value) pairs, step =
    the bin's centre in percent of the episode (5, 15, ..., 95): MLflow line charts of
    step-indexed metrics overlay cells on one progress axis."""
    out: dict[str, dict[str, list[tuple[int, float]]]] = {}
    modes = data.steps.groupby("cell_id", observed=True)["mode"].first()
    refining = sorted(str(c) for c, m in modes.items() if m in REFINING)
    for column, name, cells in (("r_img", "r_img", None), ("gate", "gate_rate", refining)):
        if cells == []:
            continue
        b = binned(data.steps, column, bins, cells)
        for r in b.itertuples():
            step = round(100 * float(r.x))
            out.setdefault(str(r.cell_id), {}).setdefault(name, []).append((step, float(r.mean)))
    return out


def save(fig: Figure, path: Path) -> Path:
    return write_atomic(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))


def write_figures(
    run_dir: str | Path, data: RunData | None = None
) -> tuple[dict[str, Path], dict[str, str]]:
    """Build and save the run's figures to RUN_DIR/figures/<name>.png (stale ones removed);
    ``data``: the run as the caller read it already.

    Returns (name -> path, name -> why skipped)."""
    run_dir = Path(run_dir)
    figs = build_figures(data if data is not None else load_run(run_dir))
    out_dir = run_dir / FIGURES_DIR
    paths = {name: save(fig, out_dir / f"{name}.png") for name, fig in figs.built.items()}
    for name in figs.skipped:
        (out_dir / f"{name}.png").unlink(missing_ok=True)
    return paths, figs.skipped
