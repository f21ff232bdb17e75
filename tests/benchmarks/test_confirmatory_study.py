"""benchmarks/confirmatory_study.py: a study dir's observations become the results file with the
evidence a reader checks a declared claim by (the study file's commit before the first episode,
the endpoints' hash, each run's tau and hardware), and a study file with uncommitted changes is
refused. The study is the smoke's fakes, two training seeds of one member, run through the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline import cli
from tests.benchmarks import load_script

ROOT = Path(__file__).resolve().parents[2]
SMOKE = ROOT / "conf" / "smoke.yaml"


confirmatory_study = load_script(ROOT / "benchmarks" / "confirmatory_study.py")


STUDY = """
name: fake_confirmatory
set: [episodes_per_task=3, "grid=[{mode: [diagnose, E, random]}]", executor.kind=inline,
      executor.workers=1, tracking.enabled=false, idr.tau=calibrated,
      "calibration={episodes_per_task: 10}", "backbone.params.noise_std=0.3"]
runs:
  - {arch: fake, env: smoke, seed: 0, config: SMOKE}
  - {arch: fake, env: smoke, seed: 1, config: SMOKE, set: [backbone.params.gain=3.0]}
  - {arch: other, env: smoke, seed: 0, config: SMOKE, set: [backbone.params.gain=1.0]}
  - {arch: other, env: smoke, seed: 1, config: SMOKE, set: [backbone.params.gain=2.0]}
endpoints:
  primary:
    - {member: fake@smoke, compare: [E, diagnose]}
    - {member: other@smoke, compare: [E, diagnose]}
    - {member: fake@smoke, compare: [E, random]}
"""
FAKE = "fake@smoke:seed0,fake@smoke:seed1"
OTHER = "other@smoke:seed0,other@smoke:seed1"


@pytest.fixture(scope="module")
def study(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The study file and its dir, holding the member ``fake`` alone (``--only``)."""
    tmp = tmp_path_factory.mktemp("study")
    study = tmp / "study.yaml"
    study.write_text(STUDY.replace("SMOKE", str(SMOKE)))
    out = tmp / "out"
    assert cli.main(["study", str(study), "--out", str(out), "--only", FAKE]) == 0
    return study, out


def test_the_results_file_holds_the_claim_and_its_evidence(study, tmp_path: Path) -> None:
    _, study_dir = study
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
    assert [(r["member"], r["reference"], r["ran"]) for r in primary] == [
        ("fake@smoke", "diagnose", True),
        ("other@smoke", "diagnose", False),  # left out by --only
        ("fake@smoke", "random", True),
    ]
    assert all(r["p_holm"] >= r["p"] for r in primary if r["ran"])
    assert data["wall_minutes"] > 0 and data["machine"]["cpu_model"]

    # the docs render every primary endpoint, pooled member and run from this file
    hook = load_script(ROOT / "docs" / "hooks" / "results_tables.py")
    md = hook.confirmatory_metaworld(data)
    assert "declared before its data: yes" in md and data["commit"][:12] in md
    rows = [line for line in md.splitlines() if line.startswith("| fake@smoke |")]
    assert [r.split(" | ")[1] for r in rows[:2]] == ["E vs diagnose", "E vs random"]
    assert f"{primary[0]['p_holm']:.2g}" in rows[0] and f"{primary[2]['p_holm']:.2g}" in rows[1]
    assert "| other@smoke | E vs diagnose | not run |" in md
    assert "| fake@smoke:seed0 |" in md and "| fake@smoke:seed1 |" in md
    assert "(held_out)" in md


def test_a_member_run_later_is_merged_and_holm_is_computed_again(study, tmp_path: Path):
    from pipeline.results.power import holm

    study_file, study_dir = study
    out = tmp_path / "confirmatory.json"
    assert confirmatory_study.main([str(study_dir), "--out", str(out)]) == 0
    partial = json.loads(out.read_text())["comparisons"]["primary"]
    # the other member, run into the same study dir later (a second --only), then merged
    assert cli.main(["study", str(study_file), "--out", str(study_dir), "--only", OTHER]) == 0
    assert confirmatory_study.main([str(study_dir), "--out", str(out), "--merge"]) == 0
    data = json.loads(out.read_text())
    primary = data["comparisons"]["primary"]
    assert [r["ran"] for r in primary] == [True, True, True]
    assert primary[0] == {**partial[0], "p_holm": primary[0]["p_holm"]}  # kept as it ran
    assert [r["p_holm"] for r in primary] == pytest.approx(holm([r["p"] for r in primary]))
    # the partial file's adjusted p bounded the complete family's from above
    assert primary[0]["p_holm"] <= partial[0]["p_holm"] + 1e-12
    assert set(data["run_records"]) == {*FAKE.split(","), *OTHER.split(",")}
    assert {m["member"] for m in data["members"]} >= {"fake@smoke", "other@smoke"}
    assert data["rimg_vs_gain"]["members"] and len(data["machines"]) == 1
    # a file of another declaration is never merged into
    other = json.loads(out.read_text()) | {"endpoints_hash": "0" * 64}
    out.write_text(json.dumps(other))
    with pytest.raises(SystemExit, match="never merged"):
        confirmatory_study.main([str(study_dir), "--out", str(out), "--merge"])


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
