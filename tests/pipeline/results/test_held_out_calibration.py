"""Held-out tau calibration (a ``calibration:`` block): tau comes from the diagnose cell's own
held-out episodes, which appear in no table of the run; bad blocks are refused before any
episode, naming the field and the fix."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.reporting.run_data import load_run
from pipeline.results.aggregate import paired_vs_baseline
from pipeline.results.store import RunStore
from pipeline.rundir import HELD_OUT_DIR

CONF = Path(__file__).resolve().parents[3] / "conf"
FAST = ["executor.kind=inline", "executor.workers=1", "tracking.enabled=false"]
CALIBRATED = [*FAST, "grid=[{mode: [diagnose, E]}]", "idr.tau=calibrated"]
TASKS = "env.tasks=[reach, reach_chain, reach@image_blackout:1]"


def _cfg(*extra: str):
    return load_config(CONF / "smoke.yaml", [*CALIBRATED, *extra])


def test_tau_comes_only_from_the_held_out_episodes(tmp_path: Path) -> None:
    cfg = _cfg(TASKS, "calibration={episodes_per_task: 10, first_episode: 100}")
    plan = plan_run(cfg, tmp_path / "run")
    # the diagnose cell alone, on the tasks but the image-zeroed control, episodes 100..109
    assert plan.held_out is not None
    assert {s.cell_id for s in plan.held_out} == {"diagnose"}
    assert sorted({s.task_id for s in plan.held_out}) == ["reach", "reach_chain"]
    assert sorted({s.episode_index for s in plan.held_out}) == list(range(100, 110))
    summary = execute(plan)
    assert summary.errors == 0 and summary.stored == 3 * 2 * 3 + 2 * 10

    held = RunStore(tmp_path / "run" / HELD_OUT_DIR, read_only=True)
    held_steps = held.steps().to_pandas()
    assert set(held_steps.episode_index) == set(range(100, 110))
    expected = held_steps.loc[held_steps.cell_id == "diagnose", "e_img"].astype(float).mean()
    saved = json.loads((tmp_path / "run" / "calibration.json").read_text())
    tau = saved["cells"]["E"]["tau"]["fake_marker"]
    assert tau == pytest.approx(expected, rel=1e-6)
    assert saved["fitted_on"] == "held_out"
    assert saved["held_out"]["controls"] == ["reach@image_blackout:1"]
    assert saved["inferences"] == len(held_steps)

    # the evaluated diagnose cell's own mean (control included) is another number: tau did not
    # come from it
    run = RunStore(tmp_path / "run", read_only=True)
    steps = run.steps().to_pandas()
    evaluated = steps.loc[steps.cell_id == "diagnose", "e_img"].astype(float).mean()
    assert abs(evaluated - tau) > 1e-3
    # the calibrated cell ran with it, and its gate follows it
    eps = run.episodes().to_pandas()
    assert eps.loc[eps.cell_id == "E", "tau"].eq(tau).all()
    e_steps = steps[steps.cell_id == "E"]
    assert ((e_steps.e_img < tau) == (e_steps.gate == 1.0)).all()

    # no held-out episode in the run's tables, comparisons or report
    data = load_run(tmp_path / "run")
    assert set(data.episodes.episode_index) == {0, 1, 2}
    assert set(data.steps.episode_index) <= {0, 1, 2}
    assert len(data.episodes) == 18
    (pair,) = paired_vs_baseline(data.episodes, baseline="diagnose")
    assert pair.n_pairs == 9
    report = (tmp_path / "run" / "report.md").read_text()
    assert "fitted on 10 held-out episodes per task (seed 0, episodes 100-109" in report
    assert "controls kept out: reach@image_blackout:1" in report

    # resume: nothing reruns, tau recomputed from the same held-out episodes
    again = execute(plan_run(cfg, tmp_path / "run"))
    assert again.stored == 0 and again.skipped == 38
    assert json.loads((tmp_path / "run" / "calibration.json").read_text()) == saved


def test_without_a_block_tau_is_fitted_on_the_evaluated_episodes(tmp_path: Path) -> None:
    cfg = _cfg("episodes_per_task=2")
    plan = plan_run(cfg, tmp_path / "run")
    assert plan.held_out is None
    execute(plan)
    assert not (tmp_path / "run" / HELD_OUT_DIR).exists()
    steps = RunStore(tmp_path / "run", read_only=True).steps().to_pandas()
    saved = json.loads((tmp_path / "run" / "calibration.json").read_text())
    expected = steps.loc[steps.cell_id == "diagnose", "e_img"].astype(float).mean()
    assert saved["cells"]["E"]["tau"]["fake_marker"] == pytest.approx(expected, rel=1e-6)
    assert saved["fitted_on"] == "evaluated"
    assert "τ fitted on the evaluated episodes." in (tmp_path / "run" / "report.md").read_text()


def test_a_block_leaves_the_fingerprint_of_a_config_without_one_as_it_was() -> None:
    plain = _cfg()
    assert plain.fingerprint() == load_config(CONF / "smoke.yaml", CALIBRATED).fingerprint()
    assert _cfg("calibration={episodes_per_task: 10}").fingerprint() != plain.fingerprint()


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        (
            ["episodes_per_task=5", "calibration={first_episode: 3}"],
            r"calibration\.first_episode: the held-out episodes 3-12 overlap the evaluated "
            r"episodes 0-4 .*first_episode=5",
        ),
        (
            ["calibration={episodes_per_task: 4}"],
            r"calibration\.episodes_per_task: 4 held-out .* at least 10",
        ),
        (
            [TASKS, "calibration={tasks: [reach, 'reach@image_blackout:1']}"],
            r"calibration\.tasks: \['reach@image_blackout:1'\] are controls",
        ),
        (
            ["calibration={tasks: [reach], controls: [reach]}"],
            r"calibration\.tasks: \['reach'\] are controls",
        ),
        (
            ["calibration={controls: [diagnose]}"],
            r"calibration\.controls: 'diagnose' is the diagnose cell that fits tau of \['E'\]",
        ),
    ],
)
def test_a_bad_block_is_refused_naming_the_field(overrides: list[str], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        _cfg(*overrides)


def test_a_block_without_a_calibrated_cell_is_refused() -> None:
    with pytest.raises(ConfigError, match=r"calibration: .* no cell has one"):
        load_config(CONF / "smoke.yaml", [*FAST, "calibration={episodes_per_task: 10}"])


@pytest.mark.parametrize(
    ("block", "match"),
    [
        ("{tasks: [reach, push]}", r"calibration\.tasks: \['push'\] are not tasks of this run"),
        ("{controls: [rech]}", r"calibration\.controls: \['rech'\] name neither a task"),
    ],
)
def test_names_the_run_lacks_are_refused_before_any_episode(
    tmp_path: Path, block: str, match: str
) -> None:
    with pytest.raises(ConfigError, match=match):
        plan_run(_cfg(f"calibration={block}"), tmp_path / "run")
    assert not list((tmp_path / "run").glob("**/*.parquet"))


def test_the_progress_count_runs_on_through_the_held_out_stage(tmp_path, monkeypatch) -> None:
    """The held-out episodes are stored by a writer of their own: while they run, the run's
    stored episodes stay counted, so done only grows, and ends at the whole total."""
    from pipeline.execution.progress import Progress

    seen: list[tuple[int, int]] = []
    monkeypatch.setattr(Progress, "update", lambda self, done, ok, *_: seen.append((done, ok)))
    cfg = _cfg("env.tasks=[reach]", "calibration={episodes_per_task: 10}")
    summary = execute(plan_run(cfg, tmp_path / "run"))
    done = [d for d, _ in seen]
    assert done == sorted(done) and done[-1] == summary.total == 3 * 2 + 10
    assert all(ok <= d for d, ok in seen)  # never more successes than episodes shown
