"""report.md from the Parquet files alone (``idr-eval report RUN_DIR`` rebuilds it).

The figures (``pipeline.reporting.figures``) are saved next to it in ``figures/`` and embedded; a figure
that fails is reported in the text, never fails the report.
"""

from __future__ import annotations

import json
import logging
import math
from collections.abc import Callable
from pathlib import Path

import pandas as pd

from pipeline.reporting.methods import methods_table
from pipeline.reporting.suite_sections import suite_sections
from pipeline.results import aggregate as agg
from pipeline.results.calibration import fitted_on_text, read_calibration
from pipeline.results.store import RunStore
from pipeline.rundir import read_run_json

log = logging.getLogger("idr_eval.report")


def _pct(x: float) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.1f}"


def _num(x: float, digits: int = 3) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}g}"


def _ci(low: float, high: float) -> str:
    return f"[{_pct(low)}, {_pct(high)}]"


def _md(headers: list[str], rows: list[list[object]]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(lines)


def main_table(episodes: pd.DataFrame) -> str:
    """Rows = cells, columns = suites and Avg (success %, Wilson 95%), Δ vs baseline."""
    suites = agg.success_by_suite(episodes)
    overall = agg.success_overall(episodes).set_index("cell_id")
    diffs = {d.cell_id: d for d in agg.paired_vs_baseline(episodes)}
    suite_names = sorted(suites["suite"].unique())
    ref = agg.reference_cell(set(overall.index)) or "baseline"
    headers = ["cell", *suite_names, "Avg", f"Δ vs {ref} (95% CI)", "p (McNemar)", "errors"]
    rows = []
    ref = agg.reference_cell(set(overall.index))
    for cell in sorted(overall.index, key=lambda c: (c != ref, c)):
        r = [cell]
        for s in suite_names:
            m = suites[(suites["cell_id"] == cell) & (suites["suite"] == s)]
            r.append(_pct(m["success_rate"].iloc[0]) if len(m) else "–")
        o = overall.loc[cell]
        r.append(f"{_pct(o['success_rate'])} [{_pct(o['ci_low'])}, {_pct(o['ci_high'])}]")
        d = diffs.get(cell)
        r.append(
            f"{100 * d.diff:+.1f} [{100 * d.ci_low:+.1f}, {100 * d.ci_high:+.1f}] (n={d.n_pairs})"
            if d
            else "–"
        )
        r.append(_num(d.p_value) if d else "–")
        r.append(str(int(o["errors"])))
        rows.append(r)
    return _md(headers, rows)


# -- the tables after the main one: each a function of the episodes -> (title, headers, rows),
# or None when it has nothing to show; the report prints them in TABLES' order -----------------
Table = tuple[str, list[str], list[list[object]]]


def task_table(episodes: pd.DataFrame) -> Table:
    t = agg.success_by_task(episodes)
    rows = [
        [
            r.cell_id,
            r.suite,
            r.task_id,
            r.n,
            _pct(r.success_rate),
            _ci(r.ci_low, r.ci_high),
            r.errors,
        ]
        for r in t.itertuples()
    ]
    headers = ["cell", "suite", "task", "n", "success", "95% CI", "errors"]
    return "Success by task (%, Wilson 95% interval)", headers, rows


def chain_table(episodes: pd.DataFrame) -> Table | None:
    chains = agg.chain_metrics(episodes)
    if chains.empty:
        return None
    total = int(chains["subtasks_total"].max())
    levels = [f"rate_{i}of{total}" for i in range(1, total + 1)]
    rows = [
        [
            r["cell_id"],
            r["task_id"],
            r["n"],
            *[_pct(r.get(c, float("nan"))) for c in levels],
            f"{r['avg_len']:.2f} [{r['avg_len_low']:.2f}, {r['avg_len_high']:.2f}]",
        ]
        for r in chains.to_dict("records")
    ]
    headers = ["cell", "task", "n", *[f"{i}/{total}" for i in range(1, total + 1)], "Avg Len"]
    return "Chains: i/N completion rates (%) and Avg Len (bootstrap 95%)", headers, rows


def cause_table(episodes: pd.DataFrame) -> Table | None:
    causes = agg.failure_causes(episodes)
    if causes.empty:
        return None
    cols = list(causes.columns[len(agg.FAILURE_KEYS) :])
    rows = [
        [r["cell_id"], r["task_id"], r["n"], r["failed"], *[r[c] for c in cols]]
        for r in causes.to_dict("records")
    ]
    title = "Failures by cause (episodes without success; errors excluded)"
    return title, ["cell", "task", "n", "failed", *cols], rows


def time_table(episodes: pd.DataFrame) -> Table:
    rows = [
        [
            r.cell_id,
            r.suite,
            _num(r.sim_seconds_to_success),
            _num(r.wall_seconds_mean),
            _num(r.inference_ms_mean),
        ]
        for r in agg.completion_times(episodes).itertuples()
    ]
    headers = ["cell", "suite", "sim s to success", "wall s / episode", "inference ms"]
    return "Completion time", headers, rows


def diagnostics_table(episodes: pd.DataFrame) -> Table:
    rows = [
        [r.cell_id, _num(r.gate_rate), _num(r.e_img_mean), _num(r.e_prop_mean), _num(r.r_img_mean)]
        for r in agg.diagnostics_by_cell(episodes).itertuples()
    ]
    headers = ["cell", "gate rate", "E_img", "E_prop", "R_img"]
    return "Diagnostics (means over episodes)", headers, rows


def error_table(episodes: pd.DataFrame) -> Table | None:
    errs = agg.errors(episodes)
    if errs.empty:
        return None
    rows = [
        [r.cell_id, r.task_id, r.episode_index, r.attempt, str(r.error).splitlines()[0][:120]]
        for r in errs.itertuples()
    ]
    title = "Errors (not counted as failures)"
    return title, ["cell", "task", "episode", "attempts", "error"], rows


TABLES: tuple[Callable[[pd.DataFrame], Table | None], ...] = (
    task_table,
    chain_table,
    cause_table,
    time_table,
    diagnostics_table,
)


def perturbation_section(episodes: pd.DataFrame) -> list[str]:
    """Success per cell x perturbation (%, with the paired Δ against the reference on the
    same perturbed tasks) where the run's tasks are perturbed; nothing otherwise."""
    if not agg.any_perturbed(episodes):
        return []
    tagged = agg.with_perturbation(episodes)
    rates = agg.success_by_perturbation(tagged)
    perts = sorted(rates["perturbation"].unique(), key=lambda p: (p != "none", p))
    cells = sorted(rates["cell_id"].unique())
    diffs: dict[tuple[str, str], str] = {}
    for pert, g in tagged.groupby("perturbation"):
        for d in agg.paired_vs_baseline(g):
            diffs[(d.cell_id, str(pert))] = f" ({100 * d.diff:+.1f})"
    rows = []
    for cell in cells:
        r = [cell]
        for pert in perts:
            m = rates[(rates["cell_id"] == cell) & (rates["perturbation"] == pert)]
            r.append(
                _pct(m["success_rate"].iloc[0]) + diffs.get((cell, pert), "") if len(m) else "–"
            )
        rows.append(r)
    return [
        "",
        "## Success rate (%) by perturbation (Δ vs the reference cell on the same tasks, pp)",
        "",
        _md(["cell", *perts], rows),
    ]


def calibration_section(run_dir: Path) -> list[str]:
    calib = read_calibration(run_dir)
    if not calib or not calib.get("cells"):
        return []
    rows = [
        [cell, c["spec"], c["effect"], c["source_cell"], suite, _num(tau, 4)]
        for cell, c in calib["cells"].items()
        for suite, tau in c["tau"].items()
    ]
    return [
        "",
        "## τ calibration (per backbone x suite, from the diagnose cell)",
        "",
        f"τ {fitted_on_text(calib)}.",
        "",
        _md(["cell", "tau", "statistic of", "measured in", "suite", "value"], rows),
    ]


def figures_section(figures: tuple[dict[str, Path], dict[str, str]] | str | None) -> list[str]:
    if figures is None:
        return []
    parts = ["", "## Figures", ""]
    if isinstance(figures, str):
        return [*parts, f"Figures failed: {figures}"]
    from pipeline.reporting.figures import CAPTIONS

    paths, skipped = figures
    for name, path in paths.items():
        caption = CAPTIONS.get(name, name)
        parts += [f"**{caption}**", "", f"![{caption}]({path.parent.name}/{path.name})", ""]
    if skipped:
        parts.append(
            "Not drawn: " + "; ".join(f"{name} ({why})" for name, why in skipped.items()) + "."
        )
    return parts


def _file_health(store: RunStore) -> list[str]:
    """Lines on unreadable Parquet files: quarantined by a driver, or skipped by this reader."""
    lines = []
    if q := store.quarantined_files():
        lines.append(
            f"{len(q)} unreadable Parquet files are in `quarantine/` (moved aside with their "
            "partner batches: their episodes count as not stored, and a resume runs them again)."
        )
    if bad := sorted({*store.unreadable, *store.unreadable_files()}):
        lines.append(
            f"{len(bad)} unreadable Parquet files skipped here: {', '.join(bad[:5])}; "
            "`idr-eval run` on this run dir quarantines them and runs their episodes again."
        )
    return lines


def protocol_line(protocol: dict[str, object]) -> str:
    """An env protocol (run.json's ``protocol``) in one line."""
    name = protocol.get("name", "(unnamed)")
    rest = ", ".join(f"{k} {v}" for k, v in protocol.items() if k != "name")
    return f"{name} ({rest})" if rest else str(name)


def _protocol(run_dir: Path) -> list[str]:
    try:
        protocol = (read_run_json(run_dir) or {}).get("protocol")
    except (OSError, json.JSONDecodeError):
        return []
    return [f"Env protocol: {protocol_line(protocol)}.", ""] if protocol else []


def numerics_lines(episodes: pd.DataFrame) -> list[str]:
    """Each (numerical path, hardware class) the episodes ran on, with its episode count, and a
    warning when a resumed run mixes them (--allow-numerics-change): those episodes differ in
    float rounding. Episodes of run dirs made before the hardware was recorded: "unknown"."""
    if "numerics" not in episodes:
        return []
    rows = episodes[episodes["numerics"].notna()]
    if rows.empty:
        return []
    hardware = (
        rows["hardware"].fillna("unknown hardware")
        if "hardware" in rows
        else pd.Series("unknown hardware", index=rows.index)
    )
    counts = pd.DataFrame({"path": rows["numerics"], "hw": hardware}).value_counts()
    if len(counts) == 1:
        (path, hw), n = next(iter(counts.items()))
        return [f"Numerical path: `{path}` on `{hw}` ({n} episode{'' if n == 1 else 's'})."]
    combos = ", ".join(
        f"`{p}` on `{h}` ({n} episode{'' if n == 1 else 's'})"
        for (p, h), n in sorted(counts.items())
    )
    return [
        f"**Mixed numerics**: {combos}. Episodes of different paths or hardware differ in float "
        "rounding (see docs/reproducibility.md)."
    ]


def _methods_section(store: RunStore, episodes: pd.DataFrame, focus: str | None) -> list[str]:
    """The methods table (``pipeline.reporting.methods``) of a run with several methods."""
    if focus is not None:
        return []
    columns = ["cell_id", "pass_rows", "executed_steps", "inference_ms"]
    built = methods_table(episodes, store.steps(columns=columns))
    if built is None:
        return []
    title, headers, rows = built
    return ["", f"## {title}", "", _md(headers, rows)]


def build_report(
    run_dir: str | Path,
    figures: tuple[dict[str, Path], dict[str, str]] | str | None = None,
    *,
    focus: str | None = None,
    episodes: pd.DataFrame | None = None,
) -> str:
    """The report text; ``figures``: what ``write_figures`` returned (or why it failed).

    ``focus``: one cell's slice (its MLflow child run's report): the main table holds the cell
    and the reference it is paired with, every other table the cell alone. ``episodes``: the
    run's episodes where the caller has them read already."""
    run_dir = Path(run_dir)
    store = RunStore(run_dir, read_only=True)
    if episodes is None:
        episodes = store.episodes().to_pandas()
    title = (
        f"# Cell `{focus}` of run `{run_dir.name}`"
        if focus
        else f"# IDR evaluation report: `{run_dir.name}`"
    )
    parts = [title, "", *_protocol(run_dir)]
    files = [] if focus else _file_health(store)
    if focus is not None:
        ref = agg.reference_cell(set(episodes["cell_id"]))
        paired = episodes[episodes["cell_id"].isin({focus, ref})]
        episodes = episodes[episodes["cell_id"] == focus]
    if episodes.empty:
        return "\n".join([*parts, "No episodes stored yet.", *files]) + "\n"
    n_err = int(episodes["error"].notna().sum())
    parts += [
        f"{len(episodes)} episodes, {episodes['cell_id'].nunique()} cells, "
        f"{episodes['task_id'].nunique()} tasks; {n_err} error rows (excluded from rates).",
        *numerics_lines(episodes),
        *files,
        "",
        "## Success rate (%) by suite, with the paired difference against baseline",
        "",
        main_table(paired if focus is not None else episodes),
        *_methods_section(store, episodes, focus),
        *perturbation_section(paired if focus is not None else episodes),
        *suite_sections(episodes),
    ]
    for table in TABLES:
        if (built := table(episodes)) is not None:
            title, headers, rows = built
            parts += ["", f"## {title}", "", _md(headers, rows)]
    parts += [] if focus else calibration_section(run_dir)
    parts += figures_section(figures)
    if (built := error_table(episodes)) is not None:
        title, headers, rows = built
        parts += ["", f"## {title}", "", _md(headers, rows)]
    return "\n".join(parts) + "\n"
