"""benchmarks/confirmatory_study.py: a study dir's observations become the results file with the
evidence a reader checks a declared claim by (the study file's commit before the first episode,
the endpoints' hash, each run's tau and hardware), and a study file with uncommitted changes is
refused. The study is the smoke's fakes, two training seeds of one member, run through the CLI."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path
from typing import Any

import pytest

from pipeline import cli

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "conf" / "smoke.yaml"


def _load(name: str, path: Path) -> Any:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


confirmatory_study = _load("confirmatory_study", ROOT / "benchmarks" / "confirmatory_study.py")


@pytest.fixture(scope="module")
def study_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    tmp = tmp_path_factory.mktemp("study")
    study = tmp / "study.yaml"
    study.write_text(
        f"""
name: fake_confirmatory
set: [episodes_per_task=3, "grid=[{{mode: [diagnose, E, random]}}]", executor.kind=inline,
      executor.workers=1, tracking.enabled=false, idr.tau=calibrated,
      "calibration={{episodes_per_task: 10}}", "backbone.params.noise_std=0.3"]
runs:
  - {{arch: fake, env: smoke, seed: 0, config: {SMOKE}}}
  - {{arch: fake, env: smoke, seed: 1, config: {SMOKE}, set: [backbone.params.gain=3.0]}}
endpoints:
  primary:
    - {{member: fake@smoke, compare: [E, diagnose]}}
    - {{member: fake@smoke, compare: [E, random]}}
"""
    )
    out = tmp / "out"
    assert cli.main(["study", str(study), "--out", str(out)]) == 0
    return out


def test_the_results_file_holds_the_claim_and_its_evidence(study_dir: Path, tmp_path: Path):
    out = tmp_path / "confirmatory.json"
    assert confirmatory_study.main([str(study_dir), "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    # the shipped study file was committed long before these episodes
    assert data["declared_before_data"] is True and len(data["commit"]) == 40
    pinned = json.loads((study_dir / "endpoints.json").read_text())["hash"]
    assert data["endpoints_hash"] == pinned
    assert set(data["run_records"]) == {"fake@smoke:seed0", "fake@smoke:seed1"}
    for rec in data["run_records"].values():
        assert rec["episodes"] == 3 * 2 * 3 and rec["errors"] == 0  # 3 cells x 2 tasks x 3
        assert rec["tau"]["fitted_on"] == "held_out"
        assert rec["hardware"] and rec["code_versions"]
    primary = data["comparisons"]["primary"]
    assert [(r["cell"], r["reference"], r["seeds"]) for r in primary] == [
        ("E", "diagnose", 2),
        ("E", "random", 2),
    ]
    assert all(r["p_holm"] >= r["p"] for r in primary)
    assert data["wall_minutes"] > 0 and data["machine"]["cpu_model"]

    # the docs render every primary endpoint, pooled member and run from this file
    hook = _load("results_tables", ROOT / "docs" / "hooks" / "results_tables.py")
    md = hook.confirmatory_metaworld(data)
    assert "declared before its data: yes" in md and data["commit"][:12] in md
    rows = [line for line in md.splitlines() if line.startswith("| fake@smoke |")]
    assert [r.split(" | ")[1] for r in rows[:2]] == ["E vs diagnose", "E vs random"]
    for r in primary:
        assert f"{r['p_holm']:.2g}" in rows[primary.index(r)]
    assert "| fake@smoke:seed0 |" in md and "| fake@smoke:seed1 |" in md
    assert "(held_out)" in md


def test_a_study_file_with_uncommitted_changes_is_not_the_declared_one(tmp_path: Path) -> None:
    import subprocess

    def git(*args: str) -> None:
        subprocess.run(["git", "-c", "user.name=t", "-c", "user.email=t@t", *args], cwd=tmp_path,
                       check=True, capture_output=True)  # fmt: skip

    study = Path("study.yaml")
    git("init", "-q")
    (tmp_path / study).write_text("name: declared\n")
    with pytest.raises(SystemExit, match="not committed"):
        confirmatory_study.declaration(study, tmp_path)  # never committed
    git("add", str(study))
    git("commit", "-qm", "declare")
    assert len(confirmatory_study.declaration(study, tmp_path)["commit"]) == 40
    (tmp_path / study).write_text("name: changed after the declaration\n")
    with pytest.raises(SystemExit, match="not committed"):
        confirmatory_study.declaration(study, tmp_path)
