"""Config validation: every bad input names the field; overrides are dotted and typed."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.planning.config import ConfigError, config_from_dict, load_config
from pipeline.planning.config_yaml import apply_overrides

CONF = Path(__file__).resolve().parents[3] / "conf"


def _base() -> dict:
    return {"backbone": {"kind": "fake_marker"}, "env": {"suite": "fake_marker"}}


@pytest.mark.parametrize(
    "name", ["smoke.yaml", "default.yaml", "experts.yaml", "tiny_vla.yaml", "libero_smoke.yaml"]
)
def test_presets_validate(name, tmp_path) -> None:
    """Each preset passes the whole pre-flight (suite, tasks, backbone and its params, the
    executor) and plans cells x tasks x episodes, each task in a named suite."""
    from pipeline.execution.runner import plan_run

    cfg = load_config(CONF / name)
    plan = plan_run(cfg, tmp_path / "run")
    assert plan.tasks and cfg.cells()
    expected = len(cfg.cells()) * len(plan.tasks) * cfg.episodes_per_task
    assert len(plan.all_specs()) == expected
    assert all(s.task.suite for s in plan.all_specs())
    assert {s.cell_id for s in plan.all_specs()} == {c.cell_id for c in cfg.cells()}


def test_smoke_preset_shape() -> None:
    cfg = load_config(CONF / "smoke.yaml")
    assert [c.cell_id for c in cfg.cells()] == ["baseline", "E"]
    assert cfg.env.tasks == ["reach", "reach_chain"] and cfg.episodes_per_task == 3
    assert cfg.executor.kind == "ray"


def test_overrides_are_dotted_and_yaml_typed() -> None:
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.workers=1",
            "executor.kind=inline",
            "grid=[{mode: [baseline, E, F]}]",
            "idr.alpha=0.1",
        ],
    )
    assert cfg.executor.workers == 1 and cfg.executor.kind == "inline"
    assert [c.cell_id for c in cfg.cells()] == ["baseline", "E", "F"]
    assert cfg.cells()[1].idr.alpha == 0.1


def test_unknown_key_suggests_closest() -> None:
    with pytest.raises(
        ConfigError, match=r"executor.wrokers: unknown key; did you mean 'workers'\?"
    ):
        config_from_dict({**_base(), "executor": {"wrokers": 2}})
    with pytest.raises(
        ConfigError, match=r"episodes_per_tsk: unknown key; did you mean 'episodes_per_task'"
    ):
        config_from_dict({**_base(), "episodes_per_tsk": 2})


@pytest.mark.parametrize(
    ("patch", "pattern"),
    [
        ({"episodes_per_task": "many"}, r"episodes_per_task: .*valid integer"),
        ({"episodes_per_task": 0}, r"episodes_per_task: .*greater than or equal to 1"),
        ({"executor": {"kind": "slurm"}}, r"executor.kind: .*'ray' or 'inline'"),
        (
            {"intervention": {"strategy": "blur"}},
            r"intervention.strategy: .*'zero', 'mean' or 'gaussian'",
        ),
        ({"idr": {"alhpa": 0.1}}, r"idr.alhpa: unknown key; did you mean 'alpha'"),
        # an intervention key under idr: was once overridden by the intervention: defaults
        (
            {"idr": {"strategy": "mean"}},
            r"'strategy' is an intervention setting.*intervention: \{strategy: 'mean'\}",
        ),
        ({"idr": {"image_space": "raw"}}, r"'image_space' is an intervention setting"),
        ({"idr": {"alpha": -0.1}}, r"alpha=-0.1 must be a number >= 0"),
        ({"grid": [{"mode": ["Q"]}]}, r"mode='Q' is unknown"),
        ({"backbone": {}}, r"backbone.kind: required field is missing"),
    ],
)
def test_bad_values_name_the_field(patch, pattern) -> None:
    with pytest.raises(ConfigError, match=pattern):
        config_from_dict({**_base(), **patch})


def test_missing_config_file_suggests_preset(monkeypatch) -> None:
    monkeypatch.chdir(CONF.parent)
    with pytest.raises(ConfigError, match=r"not found; did you mean conf/smoke.yaml\?"):
        load_config("conf/smok.yaml")


def test_bad_override_syntax() -> None:
    with pytest.raises(ConfigError, match=r"must look like key.sub=value"):
        apply_overrides({}, ["executor.workers"])
    with pytest.raises(ConfigError, match=r"'executor' is not a section"):
        apply_overrides({"executor": 3}, ["executor.workers=2"])


def test_fingerprint_ignores_executor_but_not_grid() -> None:
    a = config_from_dict(_base())
    b = config_from_dict({**_base(), "executor": {"kind": "inline", "workers": 1}})
    c = config_from_dict({**_base(), "grid": [{"mode": ["E"]}]})
    assert a.fingerprint() == b.fingerprint() != c.fingerprint()
