"""tau calibration, the paper's rule: tau := mean E_img of the diagnose cell over its steps.

The diagnose cell executes the base action (with shared noise it is also the baseline) and
records E_img at every inference; cells with ``tau: calibrated`` are scheduled after it, with
that mean as their threshold. The value is written to RUN_DIR/calibration.json, logged to
MLflow, and recorded in every episode row (column ``tau``).

Calibration is per backbone x suite (a run has one backbone; a LIBERO run spans several
suites, and each gets its own tau), and per calibrated cell: its spec may ask for a multiple
or a percentile (``calibrated*2``, ``calibrated_q90``); the statistic is of the guided effect
(E_img, or E_prop under ``guidance: proprio``, since the gate thresholds the guided effect);
and the source is the diagnose cell with the cell's intervention settings.

Which episodes fit tau. Without a ``calibration:`` block, the diagnose cell's evaluated
episodes (the paper's rule as it was: ``make run``'s tables stay as they are). With one, the
diagnose cell runs again on held-out episodes of its own (:func:`held_out_tasks` chooses their
tasks; indices ``calibration.indices``, disjoint from the evaluated ones, under the run's seed)
into a store of their own (``RUN_DIR/calibration_episodes``), and only those fit tau; their
episodes are in no success table, paired comparison or MLflow metric of the run. Controls
(tasks under ``image_blackout``, tasks or cells in ``calibration.controls``) never enter the fit.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pandas as pd
import pyarrow.compute as pc

from pipeline.errors import ConfigError
from pipeline.planning.calibration_block import is_control_task
from pipeline.planning.grid import Cell
from pipeline.results.store import RunStore
from pipeline.rundir import CALIBRATION_FILE, write_text_atomic

if TYPE_CHECKING:
    from pipeline.planning.config import CalibrationConfig, RunConfig
    from workers.envs.base import TaskSpec


def held_out_tasks(
    cal: CalibrationConfig, tasks: Sequence[TaskSpec], cells: list[Cell]
) -> list[TaskSpec]:
    """The run's tasks whose held-out episodes fit tau: ``cal.tasks`` or every task but the
    controls. Raises ConfigError (before any episode) for a name the run lacks, or a suite of
    the run that no calibration task covers (its calibrated cells would have no tau there)."""
    ids = [t.task_id for t in tasks]
    cell_ids = {c.cell_id for c in cells}
    unknown = [c for c in cal.controls if c not in ids and c not in cell_ids]
    if unknown:
        raise ConfigError(
            f"calibration.controls: {unknown} name neither a task of this run ({ids}) nor a "
            f"cell ({sorted(cell_ids)}); name controls as the run spells them"
        )
    if cal.tasks is not None:
        missing = [t for t in cal.tasks if t not in ids]
        if missing:
            raise ConfigError(
                f"calibration.tasks: {missing} are not tasks of this run; its tasks are {ids} "
                "(calibration tasks are a subset of env.tasks x env.perturbations)"
            )
        chosen = [t for t in tasks if t.task_id in cal.tasks]
    else:
        chosen = [t for t in tasks if not is_control_task(t.task_id, cal.controls)]
    covered = {t.suite for t in chosen}
    bare = sorted({str(t.suite) for t in tasks if t.suite not in covered})
    if bare:
        raise ConfigError(
            f"calibration.tasks: no held-out task in suite {bare[0]!r}, where the calibrated "
            "cells need a tau; add one of its tasks that is not a control to calibration.tasks"
        )
    return chosen


def held_out_record(
    cfg: RunConfig, chosen: Sequence[TaskSpec], tasks: Sequence[TaskSpec]
) -> dict[str, Any]:
    """What calibration.json and the report say about the held-out episodes: those of the
    ``chosen`` tasks, and the controls among the run's ``tasks`` and cells kept out."""
    cal = cfg.calibration
    assert cal is not None
    held = cal.indices(cfg.episodes_per_task)
    controls = sorted({*cal.controls, *(t.task_id for t in tasks if is_control_task(t.task_id))})
    return {
        "episodes_per_task": cal.episodes_per_task,
        "first_episode": held.start,
        "last_episode": held.stop - 1,
        "seed": cfg.seed,
        "tasks": [t.task_id for t in chosen],
        "controls": controls,
    }


def mean_e_img(store: RunStore, cell_id: str) -> tuple[float, int]:
    """Mean E_img over all stored inferences of ``cell_id`` and how many there were."""
    steps = store.steps(columns=["cell_id", "e_img"])
    steps = steps.filter(pc.and_(pc.equal(steps["cell_id"], cell_id), pc.is_valid(steps["e_img"])))
    n = steps.num_rows
    if n == 0:
        return math.nan, 0
    return float(pc.mean(steps["e_img"]).as_py()), n


def effects_by_suite(store: RunStore, cell_id: str) -> pd.DataFrame:
    """Per inference of ``cell_id``: backbone, suite, e_img, e_prop (suite from its episode)."""
    steps = store.steps(columns=["cell_id", "task_id", "episode_index", "e_img", "e_prop"])
    steps = steps.filter(pc.equal(steps["cell_id"], cell_id)).to_pandas()
    eps = store.episodes(columns=["cell_id", "task_id", "episode_index", "backbone", "suite"])
    eps = eps.filter(pc.equal(eps["cell_id"], cell_id)).to_pandas()
    df = steps.merge(eps, on=["cell_id", "task_id", "episode_index"], how="inner")
    return df[["backbone", "suite", "e_img", "e_prop"]]


def _groups(source: str, df: pd.DataFrame) -> list[dict[str, Any]]:
    """Mean effects of one diagnose cell per backbone x suite (the record of what tau saw)."""
    df = df.dropna(subset=["e_img"])
    if df.empty:
        raise RuntimeError(
            f"tau calibration: the diagnose cell {source!r} stored no E_img (all its episodes "
            "errored?); see the errors in the report"
        )
    return [
        {
            "source_cell": source,
            "backbone": backbone,
            "suite": suite,
            "inferences": len(g),
            "e_img_mean": float(g["e_img"].astype(float).mean()),
            "e_prop_mean": float(g["e_prop"].astype(float).mean()),
        }
        for (backbone, suite), g in df.groupby(["backbone", "suite"], sort=True)
    ]


def _cell_tau(c: Cell, src: Cell | None, effects: dict[str, pd.DataFrame]) -> dict[str, Any]:
    """One calibrated cell's tau per suite: its statistic of the guided effect of ``src``."""
    spec = c.calibrated_tau
    assert spec is not None and src is not None
    effect = "e_img" if c.idr.guidance == "visual" else "e_prop"
    df = effects[src.cell_id].dropna(subset=[effect])
    taus = {
        str(suite): spec.resolve(g[effect].to_numpy(dtype=float))
        for suite, g in df.groupby("suite", sort=True)
    }
    bad = {k: v for k, v in taus.items() if not math.isfinite(v)}
    if not taus or bad:
        raise RuntimeError(
            f"tau calibration of {c.cell_id!r}: no finite {effect} from {src.cell_id!r} "
            f"for suites {sorted(bad) or 'any'}"
        )
    return {"spec": spec.text, "effect": effect, "source_cell": src.cell_id, "tau": taus}


def calibrate(
    store: RunStore,
    cells: list[Cell],
    held_out: dict[str, Any] | None = None,
    run_dir: str | Path | None = None,
) -> dict[str, Any]:
    """tau of every calibrated cell, per suite, from its diagnose cell's stored inferences.

    ``held_out``: the record of :func:`held_out_record` where ``store`` holds the held-out
    episodes (RUN_DIR/calibration_episodes); None: ``store`` is the run's own and tau is fitted
    on the evaluated episodes. ``run_dir``: where calibration.json goes (default: the store's).

    Returns (and writes to RUN_DIR/calibration.json) ``{"cells": {cell_id: {"spec", "effect",
    "source_cell", "tau": {suite: value}}}, "groups": [per diagnose cell x backbone x suite:
    inferences, mean E_img, mean E_prop]}`` plus, for the first diagnose cell pooled over
    suites, ``tau`` (mean E_img), ``inferences`` and ``source_cell``.
    Raises RuntimeError when a diagnose cell stored no effects for a suite.
    """
    calibrated = [c for c in cells if c.calibrated_tau is not None]
    sources = {c.cell_id: c.calibration_source(cells) for c in calibrated}
    missing = [cid for cid, src in sources.items() if src is None]
    if missing:
        raise RuntimeError(f"tau calibration: no diagnose cell for {missing}")
    effects = {
        src.cell_id: effects_by_suite(store, src.cell_id)
        for src in sources.values()
        if src is not None
    }
    diagnose = [c.cell_id for c in cells if c.idr.mode == "diagnose"]
    groups = [g for source, df in effects.items() for g in _groups(source, df)]
    per_cell = {c.cell_id: _cell_tau(c, sources[c.cell_id], effects) for c in calibrated}
    first = diagnose[0] if diagnose else next(iter(effects), "")
    tau, n = mean_e_img(store, first) if first else (math.nan, 0)
    result = {
        "rule": "tau := statistic of the diagnose cell's guided effect per backbone x suite",
        "fitted_on": "held_out" if held_out is not None else "evaluated",
        "held_out": held_out,
        "tau": tau,
        "inferences": n,
        "source_cell": first,
        "cells": per_cell,
        "groups": groups,
    }
    target = Path(run_dir if run_dir is not None else store.run_dir) / CALIBRATION_FILE
    write_text_atomic(target, json.dumps(result, indent=2) + "\n")
    return result


def fitted_on_text(calib: dict[str, Any]) -> str:
    """How the report says where tau came from."""
    held = calib.get("held_out")
    if calib.get("fitted_on") != "held_out" or not held:
        return "fitted on the evaluated episodes"
    tasks = ", ".join(held["tasks"])
    controls = f"; controls kept out: {', '.join(held['controls'])}" if held["controls"] else ""
    return (
        f"fitted on {held['episodes_per_task']} held-out episodes per task (seed {held['seed']}, "
        f"episodes {held['first_episode']}-{held['last_episode']}; tasks {tasks}{controls})"
    )


def read_calibration(run_dir: str | Path) -> dict[str, Any] | None:
    """RUN_DIR/calibration.json, or None when the run calibrated nothing."""
    path = Path(run_dir) / CALIBRATION_FILE
    return json.loads(path.read_text()) if path.is_file() else None
