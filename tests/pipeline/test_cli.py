"""The real CLI in a subprocess: run, resume, report, and clear errors without tracebacks."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq

ROOT = Path(__file__).resolve().parents[2]


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "pipeline.cli", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_run_resume_report(tmp_path) -> None:
    out = tmp_path / "smoke"
    r = _cli(
        "run",
        "conf/smoke.yaml",
        "--out",
        str(out),
        "executor.kind=inline",
        "tracking.enabled=false",
    )
    assert r.returncode == 0, r.stderr
    assert "12 stored" in r.stdout
    n_files = len(list(out.rglob("*.parquet")))
    assert pq.ParquetDataset(out / "episodes").read().num_rows == 12
    r = _cli(
        "run",
        "conf/smoke.yaml",
        "--out",
        str(out),
        "executor.kind=inline",
        "tracking.enabled=false",
    )
    assert r.returncode == 0 and "0 stored, 12 already stored" in r.stdout
    assert len(list(out.rglob("*.parquet"))) == n_files
    (out / "report.md").unlink()
    r = _cli("report", str(out))
    assert r.returncode == 0 and "| baseline |" in r.stdout and (out / "report.md").exists()


def test_bad_input_is_one_clear_error(tmp_path) -> None:
    r = _cli("run", "conf/smoke.yaml", "--out", str(tmp_path / "x"), "executor.wrokers=2")
    assert r.returncode == 2
    assert "executor.wrokers: unknown key; did you mean 'workers'?" in r.stderr
    assert "Traceback" not in r.stderr
    assert not (tmp_path / "x").exists()
    r = _cli("run", "conf/nope.yaml")
    assert r.returncode == 2 and "not found" in r.stderr and "Traceback" not in r.stderr


def test_a_grid_over_max_cells_needs_yes(tmp_path, capsys) -> None:
    from pipeline import cli
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import load_config

    alpha = str(ROOT / "conf" / "grids" / "alpha.yaml")
    out = tmp_path / "x"
    rc = cli.main(["run", alpha, "--out", str(out), "max_cells=4", "tracking.enabled=false"])
    err = capsys.readouterr().err
    assert rc == 2 and "Traceback" not in err
    assert (
        "max_cells: the grid gives 9 cells (90 episodes), more than max_cells=4; pass --yes" in err
    )
    assert not out.exists()  # refused before any work
    assert cli.build_parser().parse_args(["run", alpha, "--yes"]).yes
    plan = plan_run(load_config(alpha, ["max_cells=4"]), out, yes=True)
    assert len({s.cell_id for s in plan.all_specs()}) == 9


def _hub_offline_after_cli_import(env: dict[str, str]) -> str:
    """huggingface_hub's own offline flag in a fresh process that imported the CLI first."""
    code = "import pipeline.cli, huggingface_hub.constants as c; print(c.HF_HUB_OFFLINE)"
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, timeout=120
    )
    assert r.returncode == 0, r.stderr
    return r.stdout.strip()


def test_cli_is_offline_unless_told_otherwise() -> None:
    # nothing downloads from a hub at run time: a checkpoint naming a sub-model by hub id is
    # resolved from the local cache, without the hub's retries
    env = {k: v for k, v in os.environ.items() if not k.endswith("_OFFLINE")}
    assert _hub_offline_after_cli_import(env) == "True"
    assert _hub_offline_after_cli_import({**env, "HF_HUB_OFFLINE": "0"}) == "False"
