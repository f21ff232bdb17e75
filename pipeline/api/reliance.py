"""Open-loop reliance measured: each member's E_img and E_prop on the shared held-out frames
(``pipeline.api.frames``) through ``pipeline.api.diagnose``, then the figures and the report of
``pipeline.reporting.reliance``."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import pandas as pd
from idr_core.interventions import STRATEGIES, InterventionConfig

from pipeline.api.frames import FrameSet
from pipeline.reporting.reliance import intervention_record, rimg_figure, summarize, write


def measure(
    checkpoint: str | Path,
    frameset: FrameSet,
    intervention: InterventionConfig,
    batch_size: int = 32,
    seed: int = 0,
) -> pd.DataFrame:
    """E_img and E_prop of the checkpoint on every frame, beside the frames' meta."""
    from pipeline.api.diagnose import diagnose

    d = diagnose(
        checkpoint,
        frameset.frames,
        intervention=intervention,
        batch_size=batch_size,
        seed=seed,
        n_boot=10,
    )
    return frameset.meta.assign(e_img=d.e_img, e_prop=d.e_prop)


def run(
    members: dict[str, str | Path],
    frameset: FrameSet,
    out: Path,
    *,
    intervention: InterventionConfig,
    strategies_member: str | None = None,
    batch_size: int = 32,
    seed: int = 0,
) -> dict[str, Any]:
    """Measure every member on the frames, and the strategies on one; write the report."""
    if strategies_member is not None and strategies_member not in members:
        raise ValueError(
            f"--strategies {strategies_member!r}: not a member; the members are {sorted(members)}"
        )
    import time
    from datetime import date

    from workers.hardware import machine_record

    t0 = time.perf_counter()
    tables = []
    result: dict[str, Any] = {
        "machine": machine_record(),
        "date": date.today().isoformat(),
        "frames": {"source": frameset.source, "n": frameset.n, "episodes": _episodes(frameset)},
        "intervention": intervention_record(intervention),
        "members": {},
    }
    for name, ckpt in members.items():
        rows = measure(ckpt, frameset, intervention, batch_size, seed)
        tables.append(rows.assign(member=name, strategy=intervention.strategy))
        result["members"][name] = {"checkpoint": str(ckpt), **summarize(rows)}
    if strategies_member is not None:
        result["strategies"] = {"member": strategies_member, "by_strategy": {}}
        for strategy in STRATEGIES:
            iv = replace(intervention, strategy=strategy)
            if strategy == intervention.strategy:
                rows = next(t for t in tables if t["member"].iloc[0] == strategies_member).drop(
                    columns=["member", "strategy"]
                )
            else:
                rows = measure(members[strategies_member], frameset, iv, batch_size, seed)
                tables.append(rows.assign(member=strategies_member, strategy=strategy))
            result["strategies"]["by_strategy"][strategy] = rimg_figure(rows)
    result["wall_seconds"] = round(time.perf_counter() - t0, 1)
    write(out, result, pd.concat(tables, ignore_index=True))
    return result


def _episodes(frameset: FrameSet) -> int:
    return int(frameset.meta.groupby(["task_id", "episode_index"]).ngroups)
