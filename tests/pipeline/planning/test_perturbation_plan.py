"""Perturbations in a run: tasks crossed with them, refused before work when they cannot
apply, results broken down by perturbation, and the default unchanged."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.reporting.markdown import build_report
from pipeline.results.store import RunStore

CONF = Path(__file__).resolve().parents[3] / "conf"
INLINE = ["executor.kind=inline", "tracking.enabled=false", "episodes_per_task=2"]


def test_bad_perturbations_are_refused_naming_the_allowed_values(tmp_path) -> None:
    with pytest.raises(ConfigError, match=r"env.perturbations.*'fog' is unknown.*camera_shift"):
        load_config(CONF / "smoke.yaml", ["env.perturbations=[none, fog:0.3]"])
    with pytest.raises(ConfigError, match=r"env.perturbations.*0 < severity <= 1"):
        load_config(CONF / "smoke.yaml", ["env.perturbations=[light_dim:1.5]"])
    # a scene kind the suite cannot apply: refused at planning, before any file is written
    cfg = load_config(CONF / "smoke.yaml", [*INLINE, "env.perturbations=[camera_shift:0.1]"])
    with pytest.raises(ConfigError, match=r"suite 'fake_marker' cannot apply \['camera_shift'\]"):
        plan_run(cfg, tmp_path / "r")
    assert not (tmp_path / "r").exists()
    # LIBERO applies the camera, light, table and jitter kinds; distractors are tabletop-only
    cfg = load_config(CONF / "libero_smoke.yaml", [*INLINE, "env.perturbations=[distractors:2]"])
    with pytest.raises(ConfigError, match=r"'libero' cannot apply \['distractors'\] \(it applies "):
        plan_run(cfg, tmp_path / "r")
    assert not (tmp_path / "r").exists()
    cfg = load_config(CONF / "smoke.yaml", [*INLINE, "env.tasks=[nope@image_noise:0.1]"])
    with pytest.raises(ConfigError, match=r"env.tasks: \['nope@image_noise:0.1'\] not in suite"):
        plan_run(cfg, tmp_path / "r")


def test_the_default_fingerprint_is_unchanged_by_the_new_field() -> None:
    plain = load_config(CONF / "default.yaml")
    explicit = load_config(CONF / "default.yaml", ["env.perturbations=[none]"])
    noisy = load_config(CONF / "default.yaml", ["env.perturbations=[none, image_noise:0.1]"])
    assert plain.fingerprint() == explicit.fingerprint() != noisy.fingerprint()


def test_a_run_crosses_tasks_with_perturbations_and_pairs_within_each(tmp_path) -> None:
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            *INLINE,
            "env.tasks=[reach, reach_chain@image_blur:1.5]",
            "env.perturbations=[none, image_noise:0.2]",
        ],
    )
    plan = plan_run(cfg, tmp_path / "r")
    assert [t.task_id for t in plan.tasks] == [
        "reach",
        "reach@image_noise:0.2",
        "reach_chain@image_blur:1.5",
    ]
    execute(plan)
    eps = RunStore(tmp_path / "r").episodes().to_pandas()
    assert len(eps) == 2 * 3 * 2 and eps["error"].isna().all()
    # the sensor noise changes what the policy sees, so it changes outcomes on the fake
    rate = eps.groupby("task_id")["success"].mean()
    assert rate["reach"] == 1.0 and rate["reach_chain@image_blur:1.5"] < 1.0
    # kind and severity are columns of the episode rows, not only a part of the task id
    blurred = eps[eps.task_id.str.endswith("@image_blur:1.5")]
    assert set(blurred.perturbation) == {"image_blur"} and set(blurred.severity) == {1.5}
    plain = eps[~eps.task_id.str.contains("@")]
    assert set(plain.perturbation) == {"none"} and plain.severity.isna().all()
    text = build_report(tmp_path / "r")
    assert "## Success rate (%) by perturbation" in text
    assert "| cell | none | image_blur:1.5 | image_noise:0.2 |" in text
    # the unperturbed task is the same episode as in a run without perturbations
    plain = load_config(CONF / "smoke.yaml", [*INLINE, "env.tasks=[reach]"])
    execute(plan_run(plain, tmp_path / "p"))
    other = RunStore(tmp_path / "p").episodes().to_pandas()
    cols = ["cell_id", "episode_index", "success", "steps", "success_step"]
    a = eps[eps.task_id == "reach"][cols].sort_values(cols[:2]).reset_index(drop=True)
    b = other[cols].sort_values(cols[:2]).reset_index(drop=True)
    pd.testing.assert_frame_equal(a, b, check_dtype=False)


def test_mlflow_and_compare_break_results_down_by_perturbation(tmp_path) -> None:
    from mlflow import MlflowClient

    from pipeline.reporting.compare import compare

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.kind=inline",
            "episodes_per_task=2",
            f"tracking.uri={uri}",
            "env.tasks=[reach]",
            "env.perturbations=[none, image_blur:1.5]",
        ],
    )
    execute(plan_run(cfg, tmp_path / "r"))
    eps = RunStore(tmp_path / "r").episodes().to_pandas()
    client = MlflowClient(uri)
    state = (tmp_path / "r" / "tracking.json").read_text()
    children = json.loads(state)["children"]
    for cell, rid in children.items():
        m = client.get_run(rid).data.metrics
        blurred = eps[(eps.cell_id == cell) & (eps.task_id == "reach@image_blur:1.5")]
        assert m["success/perturbation/image_blur_1.5"] == pytest.approx(
            100 * blurred.success.mean(), rel=1e-3
        )
        assert m["success/perturbation/none"] == 100.0
    parent = client.get_run(json.loads(state)["parent"]).data.params
    assert parent["perturbations"] == "none,image_blur:1.5"
    text, _ = compare([tmp_path / "r"], n_boot=100)
    assert "Success rate (%) by perturbation:" in text
    assert "| run | cell | none | image_blur:1.5 |" in text
