"""The ``calibration:`` block's rules that the config alone decides: which diagnose cells fit
tau for which calibrated cells, which tasks are controls, and what a block may not say. The
episodes it runs and the fit itself are ``pipeline.results.calibration``'s."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from pipeline.planning.grid import Cell

BLACKOUT = "@image_blackout"  # a task under it sees black images: the image-zeroed control


def is_control_task(task_id: str, controls: Sequence[str] = ()) -> bool:
    """Whether ``task_id`` is a control: under ``image_blackout``, or named in ``controls``."""
    return BLACKOUT in task_id or task_id in controls


def fit_sources(cells: list[Cell]) -> dict[str, list[str]]:
    """diagnose cell id -> the calibrated cells whose tau it fits."""
    out: dict[str, list[str]] = {}
    for c in cells:
        src = c.calibration_source(cells) if c.calibrated_tau is not None else None
        if src is not None:
            out.setdefault(src.cell_id, []).append(c.cell_id)
    return out


def check_block(cfg: Any, cells: list[Cell]) -> None:
    """What a ``calibration:`` block can be checked for without the run's task list: it fits
    something, its episodes are not the evaluated ones, and no control is named for the fit.
    Raises ValueError naming the field and the fix. ``cfg``: the RunConfig being validated
    (not imported here: pipeline.planning.config calls this from its validator)."""
    cal = cfg.calibration
    assert cal is not None
    sources = fit_sources(cells)
    if not sources:
        raise ValueError(
            "calibration: the block fits tau for cells with tau: calibrated, and no cell has "
            "one; set idr.tau=calibrated (with a diagnose cell in the grid) or remove the block"
        )
    n = cfg.episodes_per_task
    held = cal.indices(n)
    if held.start < n:  # held-out indices run upward from held.start; evaluated ones are 0..n-1
        raise ValueError(
            f"calibration.first_episode: the held-out episodes {held.start}-{held.stop - 1} "
            f"overlap the evaluated episodes 0-{n - 1} (seed {cfg.seed}); set "
            f"calibration.first_episode={n} or more, or leave it out (right after the evaluated "
            "ones)"
        )
    for name in cal.controls:
        if name in sources:
            raise ValueError(
                f"calibration.controls: {name!r} is the diagnose cell that fits tau of "
                f"{sources[name]}, and a control never enters the fit; take it out of "
                "calibration.controls, or give the calibrated cells another diagnose cell"
            )
    named = [t for t in cal.tasks or [] if is_control_task(t, cal.controls)]
    if named:
        raise ValueError(
            f"calibration.tasks: {named} are controls (image_blackout, or named in "
            "calibration.controls), which never enter the fit; remove them from "
            "calibration.tasks (or leave calibration.tasks out: every task but the controls)"
        )
