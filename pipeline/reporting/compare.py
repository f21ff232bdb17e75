"""``idr-eval compare RUN_DIR...``: one table across runs, in the paper's shape.

Rows are (run, cell); columns are the success rate (%) per suite, Avg (the mean of the suites'
rates, as the paper averages), and the paired difference against the baseline: Δ of Avg with
a stratified bootstrap 95% interval (episode pairs resampled within each suite) and the exact
McNemar p-value on the discordant pairs. A cell's baseline is its own run's reference cell
(``baseline``, else ``diagnose``); a run without one is paired with the first earlier run of
the same backbone, suites and seeds that has one (its episodes have the same keys and init
states). Runs must cover the same tasks: anything else is refused before any number is
computed, naming the tasks that differ.

It also prints the MLflow Compare URL of the compared cells (and the runs-table filter that
selects them), also when the tasks differ and the table is refused: the UI can still show the
runs side by side.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.planning.config import ConfigError
from pipeline.results import aggregate as agg
from pipeline.results.store import RunStore
from pipeline.rundir import EPISODES_DIR, FIGURES_DIR

PAIR_KEY = ["suite", "task_id", "episode_index"]
#: The paper's column order for LIBERO (Spatial, Object, Goal, Long); other suites by name.
SUITE_ORDER = ("libero_spatial", "libero_object", "libero_goal", "libero_10")


@dataclass
class RunEpisodes:
    """One run to compare: a label, its directory and its episodes table."""

    label: str
    run_dir: Path | None
    episodes: pd.DataFrame


def _labels(run_dirs: list[Path]) -> list[str]:
    names = [p.name for p in run_dirs]
    if len(set(names)) == len(names):
        return names
    return [str(p) for p in run_dirs]


def load_runs(run_dirs: list[str | Path]) -> list[RunEpisodes]:
    """The runs' episodes; ConfigError for a path that is no run dir or holds no episodes."""
    paths = [Path(p) for p in run_dirs]
    if len(paths) < 1:
        raise ConfigError("compare: give at least one RUN_DIR")
    seen: set[Path] = set()
    for p in paths:
        if not (p / EPISODES_DIR).is_dir():
            raise ConfigError(f"compare: {p} is not a run dir (no episodes/ folder)")
        if p.resolve() in seen:
            raise ConfigError(f"compare: {p} is given twice")
        seen.add(p.resolve())
    runs = []
    for label, p in zip(_labels(paths), paths, strict=True):
        eps = RunStore(p, read_only=True).episodes().to_pandas()
        if eps.empty:
            raise ConfigError(f"compare: {p} has no episodes stored yet")
        runs.append(RunEpisodes(label, p, eps))
    return runs


def _task_name(suite: str, task: str) -> str:
    return task if task.startswith(f"{suite}/") else f"{suite}/{task}"


def check_same_tasks(runs: list[RunEpisodes]) -> None:
    """Refuse runs whose (suite, task) sets differ, saying which tasks each run lacks or adds."""
    sets = {
        r.label: set(zip(r.episodes["suite"], r.episodes["task_id"], strict=True)) for r in runs
    }
    first = runs[0].label
    problems = []
    for r in runs[1:]:
        lacks = sorted(sets[first] - sets[r.label])
        extra = sorted(sets[r.label] - sets[first])
        if lacks:
            problems.append(f"{r.label} lacks {', '.join(_task_name(*k) for k in lacks)}")
        if extra:
            problems.append(f"{r.label} has {', '.join(_task_name(*k) for k in extra)}")
    if problems:
        raise ConfigError(
            f"compare: the runs cover different tasks (env.tasks), so their rows are not "
            f"comparable; against {first}: " + "; ".join(problems) + ". Compare runs of the same "
            "suite and env.tasks (rerun with matching env.tasks), or compare them separately"
        )


def suite_columns(runs: list[RunEpisodes]) -> list[str]:
    names = {str(s) for r in runs for s in r.episodes["suite"].unique()}
    rank = {s: i for i, s in enumerate(SUITE_ORDER)}
    return sorted(names, key=lambda s: (rank.get(s, len(rank)), s))


def _key_frame(df: pd.DataFrame) -> pd.DataFrame:
    return df[df["error"].isna()].set_index(PAIR_KEY)


def paired_avg_diff(
    cell: pd.DataFrame, base: pd.DataFrame, n_boot: int = 2000, seed: int = 0
) -> dict[str, float]:
    """Δ of Avg (mean over suites of the per-suite success difference on shared keys), its
    stratified bootstrap 95% interval, the exact McNemar p-value and the pair count."""
    a = _key_frame(cell)["success"].astype(int).rename("cell")
    b = _key_frame(base)["success"].astype(int).rename("base")
    joined = a.to_frame().join(b, how="inner")
    if joined.empty:
        nan = float("nan")
        return {"diff": nan, "ci_low": nan, "ci_high": nan, "p_value": nan, "n_pairs": 0}
    d = (joined["cell"] - joined["base"]).groupby(level="suite")
    groups = [g.to_numpy(dtype=float) for _, g in d]
    diff = float(np.mean([g.mean() for g in groups]))
    rng = np.random.default_rng(seed)
    boots = np.zeros(n_boot)
    for g in groups:  # stratified: each suite resampled within itself
        boots += agg.bootstrap_means(g, n_boot, rng)
    boots /= len(groups)
    lo, hi = np.quantile(boots, [0.025, 0.975])
    flat = np.concatenate(groups)
    p = agg.mcnemar_exact(int((flat == 1).sum()), int((flat == -1).sum()))
    return {
        "diff": diff,
        "ci_low": float(lo),
        "ci_high": float(hi),
        "p_value": p,
        "n_pairs": int(flat.size),
    }


def _signature(df: pd.DataFrame) -> tuple:
    ok = df[df["error"].isna()]
    return (
        tuple(sorted(ok["backbone"].unique())),
        tuple(sorted(set(zip(ok["suite"], ok["task_id"], strict=True)))),
        tuple(sorted(ok["seed"].unique())),
    )


def _baselines(runs: list[RunEpisodes]) -> dict[str, tuple[str, str] | None]:
    """run label -> (run label, cell) of the baseline its cells are paired with."""
    out: dict[str, tuple[str, str] | None] = {}
    own = {r.label: agg.reference_cell(set(r.episodes["cell_id"])) for r in runs}
    for i, r in enumerate(runs):
        if own[r.label] is not None:
            out[r.label] = (r.label, str(own[r.label]))
            continue
        sig = _signature(r.episodes)
        out[r.label] = next(
            (
                (o.label, str(own[o.label]))
                for o in runs[:i]
                if own[o.label] is not None and _signature(o.episodes) == sig
            ),
            None,
        )
    return out


def compare_table(runs: list[RunEpisodes], n_boot: int = 2000) -> pd.DataFrame:
    """One row per (run, cell): success per suite (0..1), Avg, and Δ vs baseline.

    Columns: run, cell, backbone, baseline ("run/cell" or None), one column per suite, avg,
    n (episodes without error), errors, diff, ci_low, ci_high, p_value, n_pairs."""
    check_same_tasks(runs)
    suites = suite_columns(runs)
    by_label = {r.label: r for r in runs}
    bases = _baselines(runs)
    rows = []
    for r in runs:
        eps = r.episodes
        rates = agg.success_by_suite(eps)
        overall = agg.success_overall(eps).set_index("cell_id")
        base = bases[r.label]
        ref = base[1] if base and base[0] == r.label else None
        for cell in sorted(overall.index, key=lambda c: (c != ref, c)):
            mine = rates[rates["cell_id"] == cell].set_index("suite")["success_rate"]
            row: dict[str, object] = {
                "run": r.label,
                "cell": cell,
                "backbone": ",".join(sorted(eps.loc[eps["cell_id"] == cell, "backbone"].unique())),
                "baseline": f"{base[0]}/{base[1]}" if base else None,
            }
            for s in suites:
                row[s] = float(mine.get(s, np.nan))
            row["avg"] = float(np.nanmean([row[s] for s in suites])) if len(mine) else np.nan
            row["n"] = int(overall.loc[cell, "n"])
            row["errors"] = int(overall.loc[cell, "errors"])
            if base and (base[0], base[1]) != (r.label, cell):
                b_eps = by_label[base[0]].episodes
                row.update(
                    paired_avg_diff(
                        eps[eps["cell_id"] == cell], b_eps[b_eps["cell_id"] == base[1]], n_boot
                    )
                )
            rows.append(row)
    return pd.DataFrame(rows)


def _pct(x: object) -> str:
    return "–" if x is None or pd.isna(x) else f"{100 * float(x):.2f}"


def render(table: pd.DataFrame, suites: list[str]) -> str:
    """Markdown in the paper's shape: Method | suites | Avg | Δ (95% CI) | p."""
    head = ["run", "cell", *suites, "Avg", "Δ Avg vs baseline (95% CI)", "p (McNemar)", "n"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in table.to_dict("records"):
        has_diff = "diff" in r and not pd.isna(r.get("diff"))
        delta = (
            f"{100 * r['diff']:+.2f} [{100 * r['ci_low']:+.2f}, {100 * r['ci_high']:+.2f}] "
            f"(n={int(r['n_pairs'])}, vs {r['baseline']})"
            if has_diff
            else "–"
        )
        p = f"{r['p_value']:.3g}" if has_diff else "–"
        cells = [r["run"], r["cell"], *[_pct(r[s]) for s in suites], _pct(r["avg"]), delta, p]
        lines.append("| " + " | ".join(str(c) for c in [*cells, r["n"]]) + " |")
    return "\n".join(lines)


class TablesRefused(ConfigError):
    """The runs cannot share a table; ``ui_text`` still says how to see them in MLflow."""

    def __init__(self, message: str, ui_text: str) -> None:
        super().__init__(message)
        self.ui_text = ui_text


def perturbation_lines(runs: list[RunEpisodes]) -> list[str]:
    """Success (%) per (run, cell) x perturbation where the runs' tasks are perturbed."""
    if not any(agg.any_perturbed(r.episodes) for r in runs):
        return []
    rows = pd.concat(
        [agg.success_by_perturbation(r.episodes).assign(run=r.label) for r in runs],
        ignore_index=True,
    )
    perts = sorted(rows["perturbation"].unique(), key=lambda p: (p != "none", p))
    lines = ["| run | cell | " + " | ".join(perts) + " |", "|" + "---|" * (len(perts) + 2)]
    for (run, cell), g in rows.groupby(["run", "cell_id"], sort=False):
        rate = g.set_index("perturbation")["success_rate"]
        lines.append(f"| {run} | {cell} | " + " | ".join(_pct(rate.get(p)) for p in perts) + " |")
    return ["", "Success rate (%) by perturbation:", "", *lines]


def _effects_by_run(runs: list[RunEpisodes]) -> list[pd.DataFrame]:
    """Each run's reference diagnose cell's effects (empty where it has none), read once."""
    from pipeline.reporting.run_data import runs_effects

    return [runs_effects([r.run_dir]) if r.run_dir is not None else pd.DataFrame() for r in runs]


def across_suites_table(
    runs: list[RunEpisodes], effects: list[pd.DataFrame] | None = None
) -> pd.DataFrame:
    """One row per run x suite, for runs over different suites (the paper's observation 1:
    the same model's visual reliance across environments): the reference cell's success (no
    pairing: the tasks differ) and R_img of the run's reference diagnose cell. ``effects``: what
    :func:`_effects_by_run` read, where the caller has it."""
    from pipeline.reporting.run_data import rimg_matrix

    rows = []
    for r, run_effects in zip(runs, effects or _effects_by_run(runs), strict=True):
        eps = r.episodes[r.episodes["error"].isna()]
        ref = agg.reference_cell(set(eps["cell_id"]))
        rimg = rimg_matrix(run_effects) if not run_effects.empty else pd.DataFrame()
        for suite, g in eps[eps["cell_id"] == ref].groupby("suite"):
            backbone = str(g["backbone"].iloc[0])
            value = (
                rimg.loc[backbone, suite]
                if backbone in rimg.index and suite in rimg.columns
                else float("nan")
            )
            rows.append(
                {
                    "run": r.label,
                    "backbone": backbone,
                    "suite": str(suite),
                    "cell": ref,
                    "success": float(g["success"].mean()),
                    "n": len(g),
                    "r_img": float(value),
                }
            )
    return pd.DataFrame(rows)


def render_across_suites(table: pd.DataFrame) -> str:
    head = ["run", "backbone", "suite", "cell", "success (%)", "n", "R_img (diagnose)"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in table.to_dict("records"):
        rimg = "–" if pd.isna(r["r_img"]) else f"{r['r_img']:.3f}"
        cells = [r["run"], r["backbone"], r["suite"], r["cell"], _pct(r["success"]), r["n"], rimg]
        lines.append("| " + " | ".join(str(c) for c in cells) + " |")
    return "\n".join(lines)


def compare(
    run_dirs: list[str | Path],
    out: str | Path | None = None,
    n_boot: int = 2000,
    links: Callable[[list[RunEpisodes]], list[str]] | None = None,
    across_suites: bool = False,
) -> tuple[str, pd.DataFrame]:
    """Validate, build the table (and with ``out`` write OUT/compare.md plus the R_img heatmap
    across runs); returns (markdown, table). ``links``: lines appended that say where else to
    see the runs (the CLI passes pipeline.tracking.ui.mlflow_lines)."""
    runs = load_runs(run_dirs)
    ui_lines = links(runs) if links is not None else []
    if across_suites:
        return _compare_across_suites(runs, out, ui_lines)
    try:
        check_same_tasks(runs)  # before any work
    except ConfigError as e:
        raise TablesRefused(str(e), "\n".join(ui_lines) + "\n") from None
    table = compare_table(runs, n_boot=n_boot)
    suites = suite_columns(runs)
    parts = [
        f"# Comparison of {len(runs)} runs",
        "",
        "Success rate (%) per suite; Avg = mean of the suites' rates; Δ = paired difference of "
        "Avg against the baseline (stratified bootstrap 95% CI), p = exact McNemar.",
        "",
        render(table, suites),
    ]
    parts += perturbation_lines(runs)
    parts += ["", *ui_lines]
    if out is not None:
        parts += _write_heatmap(runs, Path(out))
        (Path(out) / "compare.md").write_text("\n".join(parts) + "\n")
    return "\n".join(parts) + "\n", table


def _compare_across_suites(
    runs: list[RunEpisodes], out: str | Path | None, ui_lines: list[str]
) -> tuple[str, pd.DataFrame]:
    """``compare --across-suites``: runs of one backbone on different suites side by side,
    unpaired (see :func:`across_suites_table`), with the R_img heatmap across them."""
    effects = _effects_by_run(runs)
    table = across_suites_table(runs, effects)
    parts = [
        f"# R_img and success across {len(runs)} runs, by suite",
        "",
        "Runs over different suites, unpaired: each run's reference cell (baseline, else "
        "diagnose), its success per suite, and R_img = mean E_img / (mean E_img + mean E_prop) "
        "of its diagnose cell (the paper's observation 1: the same model's visual reliance "
        "across environments). No Δ: the tasks differ.",
        "",
        render_across_suites(table),
        "",
        *ui_lines,
    ]
    if out is not None:
        parts += _write_heatmap(runs, Path(out), pd.concat(effects, ignore_index=True))
        (Path(out) / "compare.md").write_text("\n".join(parts) + "\n")
    return "\n".join(parts) + "\n", table


def _write_heatmap(
    runs: list[RunEpisodes], out: Path, effects: pd.DataFrame | None = None
) -> list[str]:
    """The R_img heatmap (backbone x suite) across the runs' diagnose cells, saved in ``out``;
    the lines that embed it (none where no run has a diagnose cell). ``effects``: the runs'
    diagnose effects where the caller read them already."""
    from pipeline.reporting.figures import rimg_heatmap, save
    from pipeline.reporting.run_data import rimg_matrix, runs_effects

    out.mkdir(parents=True, exist_ok=True)
    if effects is None:
        effects = runs_effects([r.run_dir for r in runs if r.run_dir is not None])
    if effects.empty:
        return []
    save(rimg_heatmap(rimg_matrix(effects)), out / FIGURES_DIR / "rimg_heatmap.png")
    return ["", f"![R_img per backbone x suite]({FIGURES_DIR}/rimg_heatmap.png)"]
