"""Run dirs written before the episode rows had perturbation columns (the perturbation only in
the task id) still report, compare and resume: simulated by stripping the columns from a run's
stored batches, then checked against the same run left as written."""

from __future__ import annotations

import shutil
from pathlib import Path

import pyarrow.parquet as pq

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config
from pipeline.reporting.compare import compare
from pipeline.reporting.markdown import build_report
from pipeline.results import aggregate as agg
from pipeline.results.store import RunStore

CONF = Path(__file__).resolve().parents[2] / "conf"
OVERRIDES = [
    "executor.kind=inline",
    "tracking.enabled=false",
    "episodes_per_task=2",
    "env.tasks=[reach, reach_chain@image_blur:1.5]",
    "env.perturbations=[none, image_noise:0.2]",
]
NEW_COLUMNS = ("perturbation", "severity")


def _strip(run_dir: Path) -> None:
    """The episode batches as the flat layout wrote them: without the perturbation columns."""
    for f in (run_dir / "episodes").rglob("*.parquet"):
        table = pq.read_table(f)
        pq.write_table(table.drop_columns(list(NEW_COLUMNS)), f)


def test_an_old_run_dir_reports_compares_and_resumes_like_a_new_one(tmp_path) -> None:
    cfg = load_config(CONF / "smoke.yaml", OVERRIDES)
    execute(plan_run(cfg, tmp_path / "new"))
    shutil.copytree(tmp_path / "new", tmp_path / "old")
    _strip(tmp_path / "old")
    old = RunStore(tmp_path / "old", read_only=True).episodes().to_pandas()
    assert old["perturbation"].isna().all()  # read with today's schema: nulls
    new = RunStore(tmp_path / "new", read_only=True).episodes().to_pandas()
    # the same labels, from the task ids on one side and from the columns on the other
    assert agg.perturbation_labels(old).tolist() == agg.perturbation_labels(new).tolist()
    assert set(agg.perturbation_labels(new)) == {"none", "image_noise:0.2", "image_blur:1.5"}
    assert build_report(tmp_path / "old") == build_report(tmp_path / "new").replace(
        "`new`", "`old`"
    )
    text, _ = compare([tmp_path / "old", tmp_path / "new"], n_boot=100)
    assert "| old | E |" in text and "| new | E |" in text
    # resume: a cell's batches lost; the rerun writes only those, beside the old rows
    for table in ("episodes", "steps"):
        shutil.rmtree(tmp_path / "old" / table / "cell=E")
    summary = execute(plan_run(cfg, tmp_path / "old"))
    assert (summary.skipped, summary.stored) == (2 * 3, 2 * 3)
    resumed = RunStore(tmp_path / "old", read_only=True).episodes().to_pandas()
    assert resumed.groupby("cell_id")["perturbation"].apply(lambda s: s.isna().all()).to_dict() == {
        "E": False,
        "baseline": True,
    }
    assert agg.success_by_perturbation(resumed).equals(agg.success_by_perturbation(new))


def test_a_run_dir_whose_config_misplaced_an_intervention_key_is_refused_naming_what_ran(
    tmp_path, capsys
) -> None:
    """``idr: {strategy: mean}`` was accepted and ran with strategy zero; such a run dir is
    refused on resume, and the refusal reads what its episodes actually ran with."""
    import yaml

    from pipeline.cli import main

    cfg = load_config(CONF / "smoke.yaml", [*OVERRIDES[:3], "env.tasks=[reach]"])
    run_dir = tmp_path / "run"
    execute(plan_run(cfg, run_dir))
    saved = yaml.safe_load((run_dir / "config.yaml").read_text())
    saved["idr"] = {**saved.get("idr", {}), "strategy": "mean"}  # as an old driver stored it
    (run_dir / "config.yaml").write_text(yaml.safe_dump(saved))
    (tmp_path / "old.yaml").write_text(yaml.safe_dump(saved))
    assert main(["run", str(tmp_path / "old.yaml"), "--out", str(run_dir)]) == 2
    err = capsys.readouterr().err
    assert "'strategy' is an intervention setting" in err
    stored = RunStore(run_dir, read_only=True).stored_count()
    assert f"its {stored} stored episodes ran with strategy zero" in err
