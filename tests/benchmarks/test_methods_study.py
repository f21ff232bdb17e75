"""benchmarks/methods_study.py turns a run dir's methods table into methods.json: each cell's
success inside its interval, E's placebo paired against E, and ``--merge`` keeping the runs the
file already holds (their run dirs need not exist) while a plain write holds only those given.

The run is the smoke's fakes through the real planner, executor and store (inline, no Ray)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config
from tests.benchmarks import load_script

ROOT = Path(__file__).resolve().parents[2]


methods_study = load_script(ROOT / "benchmarks" / "methods_study.py")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("methods") / "run"
    cfg = load_config(
        ROOT / "conf" / "smoke.yaml",
        [
            "tracking.enabled=false",
            "executor.kind=inline",
            "episodes_per_task=2",
            "grid=[{mode: [baseline, E, random]}]",
        ],
    )
    summary = execute(plan_run(cfg, out))
    assert summary.errors == 0
    return out


def test_a_run_dir_becomes_its_methods_table(run_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "methods.json"
    assert methods_study.main([f"fake_smoke={run_dir}", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["declared_before_data"] is False
    run = data["runs"]["fake_smoke"]
    assert run["episodes_per_task"] == 2 and run["errors"] == 0
    assert set(run["cells"]) == {"baseline", "E", "random"}
    for cell in run["cells"].values():
        assert cell["episodes"] == 4  # 2 tasks x 2 episodes
        lo, hi = cell["ci95"]
        assert lo <= cell["success"] <= hi
    assert run["cells"]["random"]["vs_E"]["n_pairs"] == 4
    assert run["cells"]["E"]["rows_per_step"] > run["cells"]["baseline"]["rows_per_step"]


def test_merge_keeps_the_other_runs_and_a_plain_write_does_not(
    run_dir: Path, tmp_path: Path
) -> None:
    out = tmp_path / "methods.json"
    kept = {"member": "kept", "cells": {"E": {"success": 0.5}}}
    out.write_text(json.dumps({"label": "exploratory", "runs": {"kept": kept, "new": {}}}))
    assert methods_study.main([f"new={run_dir}", "--out", str(out), "--merge"]) == 0
    runs = json.loads(out.read_text())["runs"]
    assert runs["kept"] == kept  # its run dir is nowhere: kept as the file held it
    assert set(runs["new"]["cells"]) == {"baseline", "E", "random"}  # replaced
    assert methods_study.main([f"new={run_dir}", "--out", str(out)]) == 0
    assert set(json.loads(out.read_text())["runs"]) == {"new"}
