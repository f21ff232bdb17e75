"""Every test-time method the smoke's fakes admit, in one grid through the real CLI path
(plan, Ray actors, store, report): no error row, each method's cost in its step rows, and the
object-hidden contrast fed the fake's marker-less image."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config
from pipeline.results.store import RunStore

CONF = Path(__file__).resolve().parents[3] / "conf"
MODES = ["baseline", "diagnose", "E", "F", "random", "shuffled", "scale_free", "cfg"]
MODES += ["ensemble", "temporal", "pcd"]
ROWS = {"baseline": 1, "temporal": 1, "cfg": 2, "pcd": 2, "ensemble": 3}  # per inference


@pytest.mark.slow
def test_one_grid_runs_every_method_the_fakes_admit(tmp_path, ray_local) -> None:
    cfg = load_config(
        CONF / "smoke.yaml",
        ["tracking.enabled=false", "executor.kind=ray", f"grid=[{{mode: [{', '.join(MODES)}]}}]"],
    )
    summary = execute(plan_run(cfg, tmp_path / "run"))
    assert summary.errors == 0 and summary.stored == len(MODES) * 6
    store = RunStore(tmp_path / "run")
    steps = store.steps().to_pandas()
    for mode in MODES:
        s = steps[steps["cell_id"] == mode]
        assert set(s["pass_rows"]) == {ROWS.get(mode, 3)}, mode
        executed = set(s["executed_steps"])
        assert executed == {1} if mode == "temporal" else max(executed) == 4, mode
    # pcd contrasts the image without the marker: its chunks differ from the baseline's
    pcd = steps[steps["cell_id"] == "pcd"].set_index(["task_id", "episode_index", "step"])
    base = steps[steps["cell_id"] == "baseline"].set_index(["task_id", "episode_index", "step"])
    first = pcd.index.intersection(base.index)[0]
    assert pcd.loc[first, "action_final"].tolist() != base.loc[first, "action_final"].tolist()
    report = (tmp_path / "run" / "report.md").read_text()
    assert "## Test-time methods side by side" in report
