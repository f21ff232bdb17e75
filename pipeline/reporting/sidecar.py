"""Reports of IDR's diagnostics sidecars: the lerobot policy type ``idr`` on a robot
(lerobot-rollout) or under lerobot-eval, read into the tables and figures of a simulated run.

A sidecar folder holds one row per env per inference (``idr_core.sidecar.COLUMNS``). Each folder
is one cell (labelled by its mode, or by ``--label``). Outcomes come from the env or the
operator:

- ``--eval-info`` (lerobot-eval's ``eval_info.json``): ``successes`` of its tasks in order; the
  sidecar's episode ``e`` of env ``i`` is lerobot-eval's episode ``e * batch_size + i``;
- ``marks.jsonl`` in the folder (``lerobot-idr-mark``): a mark belongs to the episode that
  was running when it was made.

Completion time among successful trials, latency-aware (the paper's real-world metric):
on a robot, the wall time from the episode's first chunk request to the operator's mark (the
robot's waits on inference are inside it); under lerobot-eval, the episode's control steps at
``--fps`` plus the time the loop waited for chunks (the steps are counted to the end of the last
chunk requested, an upper bound when success came inside it).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from idr_core.mark import MARKS
from idr_core.sidecar import read_sidecar

from pipeline.results import aggregate as agg

FIGURES = ("rimg_progress", "gate_progress", "inference_latency")


@dataclass(frozen=True)
class SidecarData:
    rows: pd.DataFrame  # every sidecar row, with cell_id and progress
    episodes: pd.DataFrame  # one row per (cell_id, episode, env)


def load(dirs: list[Path], labels: list[str] | None = None) -> pd.DataFrame:
    """All rows of the folders, each with its cell_id (its label, else its mode)."""
    if labels and len(labels) != len(dirs):
        raise ValueError(f"--label given {len(labels)} times for {len(dirs)} folders: one each")
    frames = []
    for i, d in enumerate(dirs):
        rows = read_sidecar(d)
        modes = sorted(set(rows["mode"]))
        rows["cell_id"] = labels[i] if labels else "+".join(modes)
        rows["source"] = str(d)
        frames.append(rows)
    rows = pd.concat(frames, ignore_index=True)
    if rows["cell_id"].nunique() < len(dirs) and not labels:
        rows["cell_id"] = rows["cell_id"] + "@" + rows["source"].map(lambda s: Path(s).name)
    return rows


def _outcomes_from_eval_info(path: Path) -> list[bool]:
    info = json.loads(path.read_text())
    out: list[bool] = []
    for task in info.get("per_task", []):
        out += [bool(s) for s in task["metrics"]["successes"]]
    if not out:
        raise ValueError(f"{path}: no per_task successes; is it lerobot-eval's eval_info.json?")
    return out


def _marks(source: str) -> pd.DataFrame:
    path = Path(source) / MARKS
    if not path.is_file():
        return pd.DataFrame(columns=["wall_time", "outcome"])
    return pd.DataFrame([json.loads(line) for line in path.read_text().splitlines() if line])


def episodes(
    rows: pd.DataFrame, eval_info: Path | None = None, fps: float | None = None
) -> pd.DataFrame:
    """One row per (cell_id, source, episode, env) with its diagnostics and outcome."""
    g = rows.groupby(["cell_id", "source", "episode", "env"], sort=True)
    gap = rows.groupby(["cell_id", "source"])["step"].apply(
        lambda s: float(np.median(np.diff(np.unique(s)))) if s.nunique() > 1 else 1.0
    )
    out = g.agg(
        inferences=("tick", "size"),
        last_step=("step", "max"),
        start=("wall_time", "min"),
        wait_s=("wait_ms", lambda s: float(np.nansum(s.astype(float))) / 1e3),
        inference_ms_mean=("inference_ms", "mean"),
        e_img_mean=("e_img", "mean"),
        e_prop_mean=("e_prop", "mean"),
        r_img_mean=("r_img", "mean"),
        gate_rate=("gate", "mean"),
        fallbacks=("fallback", lambda s: int((s.fillna("") != "").sum())),
        clipped=("clipped", lambda s: int(np.nansum(s.astype(float)))),
    ).reset_index()
    first = g.first().reset_index()
    out["start"] = first["wall_time"] - first["wait_ms"].fillna(first["inference_ms"]) / 1e3
    steps_per = out.apply(lambda r: gap[(r["cell_id"], r["source"])], axis=1)
    out["length"] = out["last_step"] + steps_per - 1
    out["success"] = pd.Series([None] * len(out), dtype=object)
    out["completion_s"] = np.nan
    if eval_info is not None:
        wins = _outcomes_from_eval_info(eval_info)
        batch = int(rows["env"].max()) + 1
        idx = out["episode"] * batch + out["env"]
        if idx.max() >= len(wins):
            raise ValueError(
                f"{eval_info} holds {len(wins)} episodes, the sidecars {int(idx.max()) + 1}: "
                "give the eval_info.json of the same lerobot-eval run"
            )
        out["success"] = [wins[i] for i in idx]
        if fps:
            sim = out["length"] / fps + out["wait_s"]
            out["completion_s"] = np.where(out["success"].astype(bool), sim, np.nan)
    for source, marks in ((s, _marks(s)) for s in out["source"].unique()):
        for _, m in marks.sort_values("wall_time").iterrows():
            mine = out[(out["source"] == source) & (out["start"] <= m["wall_time"])]
            if mine.empty:
                continue
            i = mine["start"].idxmax()
            out.at[i, "success"] = m["outcome"] == "success"
            if m["outcome"] == "success":
                out.at[i, "completion_s"] = m["wall_time"] - out.at[i, "start"]
    return out


def with_progress(rows: pd.DataFrame, eps: pd.DataFrame) -> pd.DataFrame:
    key = ["cell_id", "source", "episode", "env"]
    df = rows.merge(eps[[*key, "length"]], on=key, how="left")
    df["progress"] = ((df["step"] - 1) / df["length"].clip(lower=1)).clip(0.0, 1.0)
    return df


def summary(data: SidecarData) -> pd.DataFrame:
    """The report's table, one row per cell."""
    out = []
    for cell, e in data.episodes.groupby("cell_id", sort=True):
        r = data.rows[data.rows["cell_id"] == cell]
        known = e[e["success"].notna()]
        wins = int(known["success"].astype(bool).sum())
        lo, hi = agg.wilson(wins, len(known)) if len(known) else (np.nan, np.nan)
        out.append(
            {
                "cell_id": cell,
                "episodes": len(e),
                "inferences": len(r),
                "success": f"{wins}/{len(known)}" if len(known) else "n/a",
                "success_rate": wins / len(known) if len(known) else np.nan,
                "ci_low": lo,
                "ci_high": hi,
                "completion_s": float(e["completion_s"].mean()),
                "inference_ms_median": float(r["inference_ms"].median()),
                "inference_ms_p90": float(r["inference_ms"].quantile(0.9)),
                "wait_s_per_episode": float(e["wait_s"].mean()),
                "r_img_mean": float(r["r_img"].mean()),
                "gate_rate": float(r["gate"].mean()),
                "fallbacks": int(e["fallbacks"].sum()),
                "clipped": int(e["clipped"].sum()),
                **per_executed_step(r),
            }
        )
    return pd.DataFrame(out)


def per_executed_step(rows: pd.DataFrame) -> dict[str, float]:
    """Forward rows and inference ms per executed env step (methods infer at different
    rates: temporal ensembling at every step); NaN for a sidecar written before the policy
    recorded ``pass_rows`` and ``executed_steps``."""
    if "executed_steps" not in rows or rows["executed_steps"].isna().all():
        return {"pass_rows_per_step": np.nan, "inference_ms_per_step": np.nan}
    known = rows[rows["executed_steps"].notna()]
    steps = float(known["executed_steps"].sum())
    return {
        "pass_rows_per_step": float(known["pass_rows"].sum()) / steps,
        "inference_ms_per_step": float(known["inference_ms"].sum()) / steps,
    }


def build(dirs: list[Path], eval_info: Path | None, fps: float | None, labels: list[str] | None):
    rows = load(dirs, labels)
    eps = episodes(rows, eval_info, fps)
    return SidecarData(with_progress(rows, eps), eps)


def _fmt(x: float, digits: int = 3) -> str:
    return "—" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{digits}g}"


def markdown(table: pd.DataFrame, figures: dict[str, Path]) -> str:
    head = (
        "| cell | episodes | inferences | success | 95% CI | completion s (successes, "
        "latency-aware) | inference ms median / p90 | rows / ms per executed step | wait s / "
        "episode | R_img | gate rate | fallbacks | clipped |"
    )
    lines = ["# IDR diagnostics (sidecar)", "", head, "|" + "---|" * 13]
    for _, r in table.iterrows():
        ci = (
            "—"
            if not np.isfinite(r["ci_low"])
            else f"[{100 * r['ci_low']:.1f}, {100 * r['ci_high']:.1f}]%"
        )
        lines.append(
            f"| {r['cell_id']} | {r['episodes']} | {r['inferences']} | {r['success']} | {ci} | "
            f"{_fmt(r['completion_s'])} | {_fmt(r['inference_ms_median'])} / "
            f"{_fmt(r['inference_ms_p90'])} | {_fmt(r['pass_rows_per_step'])} / "
            f"{_fmt(r['inference_ms_per_step'])} | {_fmt(r['wait_s_per_episode'])} | "
            f"{_fmt(r['r_img_mean'])} | {_fmt(r['gate_rate'])} | {r['fallbacks']} | {r['clipped']} |"
        )
    lines += ["", *(f"![{name}](figures/{p.name})" for name, p in figures.items())]
    return "\n".join(lines) + "\n"


def latency_figure(rows: pd.DataFrame):
    from pipeline.reporting.figures import _figure

    fig = _figure()
    ax = fig.add_subplot()
    for cell, r in rows.groupby("cell_id", sort=True):
        x = np.sort(r["inference_ms"].to_numpy(dtype=float))
        ax.step(x, np.arange(1, len(x) + 1) / len(x), where="post", label=cell)
    ax.set_xlabel("per-chunk inference (ms)")
    ax.set_ylabel("share of inferences")
    ax.set_title("Inference latency (what the control loop waits at a chunk boundary)")
    ax.legend(fontsize=8, loc="best")
    return fig


def write(
    dirs: list[Path],
    out: Path,
    eval_info: Path | None = None,
    fps: float | None = None,
    labels: list[str] | None = None,
) -> Path:
    """Build the report into ``out`` (report.md, episodes.parquet, figures/); returns report.md."""
    from pipeline.reporting.figures import gate_progress, rimg_progress, save

    data = build(dirs, eval_info, fps, labels)
    cells = sorted(data.rows["cell_id"].unique())
    figs = {"inference_latency": latency_figure(data.rows)}
    diagnosed = data.rows[data.rows["r_img"].notna()]
    if not diagnosed.empty:
        figs["rimg_progress"] = rimg_progress(diagnosed, [(c, c) for c in cells], {})
        figs["gate_progress"] = gate_progress(diagnosed, cells)
    out.mkdir(parents=True, exist_ok=True)
    paths = {name: save(fig, out / "figures" / f"{name}.png") for name, fig in figs.items()}
    table = summary(data)
    data.episodes.to_parquet(out / "episodes.parquet", index=False)
    report = out / "report.md"
    report.write_text(markdown(table, paths))
    return report
