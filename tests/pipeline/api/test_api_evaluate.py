"""``pipeline.api.evaluate``: the run ``idr-eval run`` makes (same tables), resumed by a second
call, bad input refused with the CLI's message before any work, and the report's numbers."""

from __future__ import annotations

import math
import os
import subprocess
import sys
import types
from collections.abc import Iterator
from pathlib import Path

import pyarrow as pa
import pytest

from pipeline import cli
from pipeline.api import ConfigError, RunResult, evaluate, open_run
from pipeline.api.run import override_strings
from pipeline.planning.config_yaml import parse_override

ROOT = Path(__file__).resolve().parents[3]
SMOKE = ROOT / "conf" / "smoke.yaml"
FAST = ["executor.kind=inline", "tracking.enabled=false"]
KEY = ["cell_id", "task_id", "episode_index"]
# columns that say when, where and under which run id an episode ran: not what it measured
CIRCUMSTANCES = {
    "run_id", "wall_seconds", "inference_ms_mean", "worker", "node", "hardware", "started_at",
    "finished_at", "inference_ms",
}  # fmt: skip


def _measured(table: pa.Table, key: list[str]) -> list[dict[str, object]]:
    cols = [c for c in table.schema.names if c not in CIRCUMSTANCES]
    return table.select(cols).sort_by([(k, "ascending") for k in key]).to_pylist()


@pytest.fixture(scope="module", autouse=True)
def _rendering_chosen() -> Iterator[None]:
    """The inline worker runs in this process, which another test may have let import MuJoCo
    (through lerobot): the backend the worker would choose, named up front."""
    was = os.environ.get("MUJOCO_GL")
    os.environ["MUJOCO_GL"] = was or "osmesa"
    yield
    if was is None:
        os.environ.pop("MUJOCO_GL", None)


@pytest.fixture(scope="module")
def api_run(tmp_path_factory: pytest.TempPathFactory) -> RunResult:
    out = tmp_path_factory.mktemp("api") / "smoke"
    return evaluate(SMOKE, out=out, overrides=FAST)


def test_evaluate_returns_the_tables_the_cli_writes(api_run: RunResult, tmp_path: Path) -> None:
    out = tmp_path / "cli"
    r = subprocess.run(
        [sys.executable, "-m", "pipeline.cli", "run", str(SMOKE), "--out", str(out), *FAST],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    written = open_run(out)
    assert api_run.summary is not None and api_run.summary.stored == 12
    assert api_run.episodes.num_rows == 12 and api_run.steps.num_rows > 0
    assert api_run.episodes.column("success").to_pylist().count(True) == api_run.summary.successes
    assert _measured(api_run.episodes, KEY) == _measured(written.episodes, KEY)
    assert _measured(api_run.steps, [*KEY, "step"]) == _measured(written.steps, [*KEY, "step"])
    assert api_run.config.fingerprint() == written.config.fingerprint()
    assert "| baseline |" in api_run.report_path.read_text()


def test_a_second_evaluate_on_the_same_out_adds_nothing(api_run: RunResult) -> None:
    files = sorted(api_run.run_dir.rglob("*.parquet"))
    again = evaluate(SMOKE, out=api_run.run_dir, overrides=FAST)
    assert again.summary is not None
    assert (again.summary.stored, again.summary.skipped) == (0, 12)
    assert sorted(api_run.run_dir.rglob("*.parquet")) == files
    assert again.run_id == api_run.run_id
    assert _measured(again.episodes, KEY) == _measured(api_run.episodes, KEY)


def test_the_report_data_is_the_runs_numbers(api_run: RunResult) -> None:
    report = api_run.report
    eps = api_run.episodes.to_pandas()
    success = report.success.set_index("cell_id")
    assert set(success.index) == {"baseline", "E"}
    for cell, g in eps.groupby("cell_id"):
        assert success.loc[cell, "n"] == len(g)
        assert success.loc[cell, "success_rate"] == pytest.approx(g["success"].mean())
        assert success.loc[cell, "ci_low"] <= success.loc[cell, "success_rate"]
    (paired,) = report.paired  # E against the baseline on the same 6 keys
    assert paired.cell_id == "E" and paired.n_pairs == 6
    e_steps = api_run.steps.to_pandas().query("cell_id == 'E'")
    diag = report.diagnostics.set_index("cell_id")
    assert diag.loc["E", "r_img_mean"] == pytest.approx(
        eps.query("cell_id == 'E'")["r_img_mean"].mean()
    )
    assert 0 <= diag.loc["E", "r_img_mean"] <= 1 and len(e_steps) > 0
    curve = report.progress["E"]["r_img"]
    assert curve and all(0 <= x <= 100 and 0 <= y <= 1 for x, y in curve)
    assert api_run.calibration is None  # smoke's tau is a number: nothing calibrated


def test_bad_input_raises_the_clis_message_before_any_work(tmp_path: Path, capsys) -> None:
    out = tmp_path / "x"
    with pytest.raises(ConfigError) as api_error:
        evaluate(SMOKE, out=out, overrides=["executor.wrokers=2"])
    assert "executor.wrokers: unknown key; did you mean 'workers'?" in str(api_error.value)
    assert not out.exists()
    assert cli.main(["run", str(SMOKE), "--out", str(out), "executor.wrokers=2"]) == 2
    assert f"idr-eval: error: {api_error.value}\n" in capsys.readouterr().err
    # a mapping config and mapping overrides give the same refusal
    import yaml

    data = yaml.safe_load(SMOKE.read_text())
    with pytest.raises(ConfigError) as dict_error:
        evaluate(data, out=out, overrides={"executor.wrokers": 2})
    assert str(dict_error.value) == str(api_error.value).replace(str(SMOKE), "<dict>")
    assert not out.exists()
    with pytest.raises(ConfigError, match=r"not found; did you mean conf/smoke.yaml"):
        evaluate(ROOT / "conf" / "smok.yaml", out=out)
    with pytest.raises(ConfigError, match="a YAML path, a mapping or a RunConfig"):
        evaluate(42, out=out)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="is not a run dir"):
        open_run(tmp_path)


def test_inline_after_mujoco_without_a_backend_is_refused_before_any_work(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("MUJOCO_GL")
    monkeypatch.setitem(
        sys.modules, "mujoco", sys.modules.get("mujoco", types.ModuleType("mujoco"))
    )
    with pytest.raises(ConfigError, match=r"set MUJOCO_GL .* or use executor\.kind=ray"):
        evaluate(SMOKE, out=tmp_path / "x", overrides=FAST)
    assert not (tmp_path / "x").exists()


def test_mapping_overrides_parse_back_to_their_values() -> None:
    values = {"a.b": 1.5, "c": "x y", "d": [1, 2], "e": math.inf, "f": "1", "g": None, "h": True}
    got = {".".join(path): v for path, v in map(parse_override, override_strings(values))}
    assert got == values
    assert override_strings(["executor.workers=1"]) == ["executor.workers=1"]
    with pytest.raises(ConfigError, match="list of key=value strings"):
        override_strings("executor.workers=1")  # type: ignore[arg-type]
