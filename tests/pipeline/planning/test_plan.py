"""The plan as a lazy grid: the same specs, in the same order, as the nested loops it stands
for, in constant memory whatever its size."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

from pipeline.execution.runner import plan_run
from pipeline.planning.config import load_config

SMOKE = Path(__file__).resolve().parents[3] / "conf" / "smoke.yaml"
BASE = ["tracking.enabled=false", "executor.kind=inline"]


def test_the_grid_is_cells_by_tasks_by_episodes(tmp_path) -> None:
    cfg = load_config(SMOKE, [*BASE, "grid=[{mode: [baseline, diagnose, E]}]"])
    plan = plan_run(cfg, tmp_path / "run")
    want = [(c.cell_id, t.task_id, i) for c in cfg.cells() for t in plan.tasks for i in range(3)]
    assert [s.key for s in plan.specs] == want
    assert [plan.specs[i].key for i in range(len(want))] == want  # indexing agrees
    assert plan.specs[-1].key == want[-1] and plan.specs[1:3] == list(plan.specs)[1:3]
    spec = plan.specs[4]
    assert spec.task.suite == "fake_marker" and spec.code_version and spec.backbone


def test_a_huge_confirmed_plan_is_not_built(tmp_path) -> None:
    plan_run(load_config(SMOKE, BASE), tmp_path / "warm")  # imports done before measuring
    cfg = load_config(SMOKE, [*BASE, "episodes_per_task=1000000000"])
    tracemalloc.start()
    try:
        plan = plan_run(cfg, tmp_path / "run", yes=True)
        n = len(plan.all_specs())
        last = plan.all_specs()[n - 1]
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert n == 4_000_000_000 and last.episode_index == 999_999_999
    assert peak < 20 * 2**20
