"""A run's stages as grids of episodes: the cells that need no calibration, the held-out
episodes the diagnose cells fit tau on (a ``calibration:`` block), and the calibrated cells with
their tau set from the stored diagnose cell."""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

from pipeline.planning.calibration_block import fit_sources
from pipeline.planning.config import RunConfig
from pipeline.planning.grid import SpecGrid
from pipeline.planning.plan import RunPlan
from pipeline.results.calibration import calibrate, held_out_record, held_out_tasks
from pipeline.results.store import RunStore

if TYPE_CHECKING:
    from pipeline.tracking.tracker import Tracker
    from workers.envs.base import TaskSpec

log = logging.getLogger("idr_eval.runner")


def stage_grids(
    cfg: RunConfig, run_id: str, tasks: list[TaskSpec], version: str
) -> tuple[SpecGrid, SpecGrid]:
    """The first stage's grid and the calibrated one: cells with a calibrated tau run in a
    second stage, after the diagnose cell they calibrate on."""
    cells = cfg.cells()
    later = {c.cell_id for c in cells if c.calibrated_tau}
    grid = SpecGrid(
        run_id, (), tuple(tasks), cfg.episodes_per_task, cfg.seed, cfg.backbone.kind, version
    )
    specs = grid.replace(cells=tuple(c for c in cells if c.cell_id not in later))
    return specs, grid.replace(cells=tuple(c for c in cells if c.cell_id in later))


def held_out_stage(
    cfg: RunConfig, specs: SpecGrid, tasks: list[TaskSpec]
) -> tuple[SpecGrid | None, dict[str, object] | None]:
    """With a ``calibration:`` block: the diagnose cells that fit tau, on the held-out
    episodes of the calibration tasks (pipeline.results.calibration.held_out_tasks), and the
    record of them; (None, None) without one."""
    cal = cfg.calibration
    if cal is None:
        return None, None
    cells = cfg.cells()
    chosen = held_out_tasks(cal, tasks, cells)
    sources = fit_sources(cells)
    grid = specs.replace(
        cells=tuple(c for c in specs.cells if c.cell_id in sources),
        tasks=tuple(chosen),
        episodes_per_task=cal.episodes_per_task,
        first_episode=cal.first(cfg.episodes_per_task),
    )
    return grid, held_out_record(cfg, chosen, tasks)


def calibrated_specs(plan: RunPlan, store: RunStore, tracker: Tracker | None = None) -> SpecGrid:
    """The specs of the cells with ``tau: calibrated``, their tau set from the stored
    diagnose cell (the paper's rule); logged, and recorded in MLflow when tracked. ``store``:
    the held-out episodes' store where the plan has them (plan.held_out), else the run's."""
    result = calibrate(store, plan.cfg.cells(), plan.held_out_record, plan.run_dir)
    for cell_id, c in result["cells"].items():
        log.info(
            "tau of %s (%s of %s in %s): %s",
            cell_id,
            c["spec"],
            c["effect"],
            c["source_cell"],
            ", ".join(f"{suite} {tau:.4g}" for suite, tau in c["tau"].items()),
        )
    if tracker is not None:
        tracker.log_calibration(result)
    suites = {t.suite for t in plan.calibrated.tasks}
    cells = []
    for cell in plan.calibrated.cells:
        taus = result["cells"][cell.cell_id]["tau"]
        missing = sorted(str(x) for x in suites - set(taus))
        if missing:
            raise RuntimeError(
                f"tau calibration: {cell.cell_id!r} has no tau for suite {missing[0]!r} (its "
                "diagnose cell stored no inferences there; see the errors in the report)"
            )
        cells.append(replace(cell, tau_by_suite={k: float(v) for k, v in taus.items()}))
    return plan.calibrated.replace(cells=tuple(cells))
