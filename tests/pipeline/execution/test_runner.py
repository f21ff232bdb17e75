"""Runs of the smoke preset on the fakes: inline and Ray agree; resume; refusals before work."""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.results.store import VOLATILE_COLUMNS, RunStore

CONF = Path(__file__).resolve().parents[3] / "conf"


def _episodes(run_dir: Path) -> pd.DataFrame:
    df = RunStore(run_dir).episodes().to_pandas().drop(columns=list(VOLATILE_COLUMNS))
    return df.sort_values(["cell_id", "task_id", "episode_index"]).reset_index(drop=True)


def _steps(run_dir: Path) -> pd.DataFrame:
    df = RunStore(run_dir).steps().to_pandas().drop(columns=["inference_ms", "run_id"])
    return df.sort_values(["cell_id", "task_id", "episode_index", "inference_index"]).reset_index(
        drop=True
    )


@pytest.mark.slow
def test_inline_and_ray_give_identical_tables(tmp_path, ray_local) -> None:
    """The Ray actors run under the portable numerics pins where the CPU allows them (the
    cross-machine digest test asserts them only on the machines its reference lists): the
    rows say so, and the fake's tables are those of the inline run."""
    import os

    from workers.hardware import PORTABLE_ENV, PORTABLE_ISA, check_portable_cpu

    portable = check_portable_cpu() is None
    environ = {k: os.environ.get(k) for k in PORTABLE_ENV}
    inline = load_config(CONF / "smoke.yaml", ["executor.kind=inline", "tracking.enabled=false"])
    ray_cfg = load_config(
        CONF / "smoke.yaml",
        ["executor.kind=ray", "tracking.enabled=false"]
        + (["executor.numerics_mode=portable"] if portable else []),
    )
    s1 = execute(plan_run(inline, tmp_path / "inline"))
    s2 = execute(plan_run(ray_cfg, tmp_path / "ray"))
    assert s1.stored == s2.stored == 12 and s1.errors == s2.errors == 0
    a, b = _episodes(tmp_path / "inline"), _episodes(tmp_path / "ray")
    if portable:
        assert set(b.pop("hardware")) == {f"portable {PORTABLE_ISA}"}
        assert set(a.pop("hardware")) != {f"portable {PORTABLE_ISA}"}  # inline: the host's
        # the actors set the pins in their own processes: this one, and what it starts later
        # (another test's drivers), keep their environment
        assert {k: os.environ.get(k) for k in PORTABLE_ENV} == environ
    pd.testing.assert_frame_equal(a, b)
    pd.testing.assert_frame_equal(_steps(tmp_path / "inline"), _steps(tmp_path / "ray"))
    assert len(s2.workers) == 2  # two actors ran
    # paired design: every cell saw the same tasks, episode indices and init states
    keys = a.groupby("cell_id")[["task_id", "episode_index", "init_state_id"]].apply(
        lambda g: sorted(map(tuple, g.to_numpy()))
    )
    assert keys["baseline"] == keys["E"]
    # the IDR cell ran the counterfactual passes; the baseline did not
    assert a.loc[a.cell_id == "E", "e_img_mean"].notna().all()
    assert a.loc[a.cell_id == "baseline", "e_img_mean"].isna().all()
    # every failed episode has a cause (the fake ends episodes only at max_steps), no success has
    assert (a.loc[~a.success, "failure"] == "timeout").all() and a.loc[
        a.success, "failure"
    ].isna().all()


def test_resume_skips_stored_keys(tmp_path) -> None:
    cfg = load_config(CONF / "smoke.yaml", ["executor.kind=inline", "tracking.enabled=false"])
    first = execute(plan_run(cfg, tmp_path / "run"))
    assert first.stored == 12
    again = execute(plan_run(cfg, tmp_path / "run"))
    assert again.skipped == 12 and again.stored == 0
    assert len(RunStore(tmp_path / "run").episodes()) == 12
    assert (tmp_path / "run" / "report.md").read_text().startswith("# IDR evaluation report")


def test_run_dir_of_another_config_is_refused(tmp_path) -> None:
    cfg = load_config(CONF / "smoke.yaml", ["executor.kind=inline", "episodes_per_task=1"])
    execute(plan_run(cfg, tmp_path / "run"))
    other = load_config(
        CONF / "smoke.yaml", ["executor.kind=inline", "episodes_per_task=1", "seed=1"]
    )
    with pytest.raises(
        ConfigError, match=r"holds results of a different config.*new --out, or delete"
    ):
        plan_run(other, tmp_path / "run")


@pytest.mark.parametrize(
    ("overrides", "pattern"),
    [
        (["env.tasks=[reach, fly]"], r"env.tasks: \['fly'\] not in suite 'fake_marker'"),
        (
            ["env.suite=fake_markr"],
            r"env.suite='fake_markr' is unknown; did you mean 'fake_marker'",
        ),
        (
            ["env.suite=workers.envs.tabletop:TabletopEnv"],
            r"names the old layout of workers/; "
            r"write env.suite: workers.envs.suites.tabletop.env:TabletopEnv",
        ),
        (["backbone.kind=fake"], r"backbone.kind='fake' is unknown"),
        (
            ["backbone.params.gian=3"],
            r"backbone.params \(backbone 'fake_marker'\): .*'gian' \('gian': did you mean 'gain'\?\); "
            r"accepted parameters: \['chunk_len', 'gain'",
        ),
        (["env.params.size=3"], r"env.params \(suite 'fake_marker'\): .*'size'"),
        (["executor.workers=64"], r"needs 64 CPUs but this machine has \d+; .*oversubscribe=true"),
    ],
)
def test_bad_input_refused_before_any_work(tmp_path, overrides, pattern) -> None:
    cfg = load_config(CONF / "smoke.yaml", overrides)
    with pytest.raises(ConfigError, match=pattern):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_non_run_dir_is_refused(tmp_path) -> None:
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not an idr-eval run dir"):
        plan_run(load_config(CONF / "smoke.yaml"), tmp_path / "run")


@pytest.mark.parametrize("preset", ["experts.yaml", "tiny_vla.yaml", "libero_smoke.yaml"])
def test_preflight_does_not_import_a_simulator(preset, tmp_path) -> None:
    """The driver checks configs before any actor starts; importing MuJoCo there would fix the
    GL backend before a worker chooses it (in inline mode the worker is the driver)."""
    import subprocess
    import sys

    code = (
        "import sys; from pipeline.planning.config import load_config; from pipeline.execution.runner import plan_run;"
        f"plan_run(load_config({str(CONF / preset)!r}), {str(tmp_path / 'run')!r});"
        "print(sorted(m for m in ('mujoco', 'robosuite', 'OpenGL') if m in sys.modules))"
    )
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=CONF.parent
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().splitlines()[-1] == "[]"


def test_rows_name_their_hardware_and_a_resume_on_other_hardware_is_refused(tmp_path, caplog):
    """Every episode row carries this host's hardware class, run.json its record; a resume on
    another class is refused naming both unless --allow-numerics-change; a run dir made before
    the class was recorded resumes with a warning."""
    import json

    from workers.hardware import hardware_class, hardware_record

    here = hardware_class(hardware_record("cpu"))
    cfg = load_config(
        CONF / "smoke.yaml",
        ["executor.kind=inline", "tracking.enabled=false", "env.tasks=[reach]"],
    )
    run = tmp_path / "run"
    execute(plan_run(cfg, run))
    rows = RunStore(run).episodes().to_pandas()
    assert set(rows["hardware"]) == {here}
    meta_path = run / "run.json"
    meta = json.loads(meta_path.read_text())
    assert meta["hardware_class"] == here and meta["hardware"][here]["cpu_model"]
    meta["hardware_class"] = "Other CPU / AVX512"
    meta_path.write_text(json.dumps(meta))
    with pytest.raises(ConfigError, match=r"was run on 'Other CPU / AVX512', this machine is"):
        plan_run(cfg, run)
    plan = plan_run(cfg, run, allow_numerics_change=True)
    execute(plan)
    meta = json.loads(meta_path.read_text())
    assert set(meta["hardware"]) == {here} and meta["hardware_class"] == here
    del meta["hardware_class"], meta["hardware"]  # as a run dir made before the record
    meta_path.write_text(json.dumps(meta))
    with caplog.at_level("WARNING"):
        execute(plan_run(cfg, run))
    assert "made before the hardware was recorded" in caplog.text
