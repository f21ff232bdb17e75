"""The terminal of a run: its plan, progress and report; libraries and actors in RUN_DIR/logs."""

from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import pytest

from pipeline.execution.run_log import RunLog

ROOT = Path(__file__).resolve().parents[3]


@pytest.fixture
def run_log():
    root = logging.getLogger()
    saved = (root.handlers[:], root.level)
    libs = {n: (logging.getLogger(n).handlers[:], logging.getLogger(n).propagate) for n in ("ray",)}
    log = RunLog()
    yield log
    root.handlers, root.level = saved[0], saved[1]
    for n, (handlers, propagate) in libs.items():
        logging.getLogger(n).handlers, logging.getLogger(n).propagate = handlers, propagate


def test_libraries_go_to_the_file_and_idr_eval_to_the_terminal(run_log, tmp_path, capsys) -> None:
    run_log.install()
    logging.getLogger("ray._private.auth").warning("Token authentication is enabled")
    logging.getLogger("idr_eval.cluster").info("Ray cluster: 1 node(s)")
    logging.getLogger("somelib").info("chatter at info")
    held = capsys.readouterr().err
    assert "Ray cluster" in held and "Token authentication" not in held and "chatter" not in held
    path = run_log.attach(tmp_path)  # what was logged before the run dir existed comes first
    logging.getLogger("ray").error("a raylet died")  # a library's error reaches both
    logging.getLogger("mlflow.store").info("Creating initial MLflow database tables")
    err = capsys.readouterr().err
    assert "a raylet died" in err and "MLflow database" not in err
    text = path.read_text()
    for line in ("Token authentication", "Ray cluster", "chatter at info", "a raylet died"):
        assert line in text, text
    assert "Creating initial MLflow database tables" in text
    assert text.index("Token authentication") < text.index("a raylet died")


def test_a_ray_run_keeps_library_and_actor_output_off_the_terminal(tmp_path) -> None:
    """`idr-eval run` on local Ray with an env that prints when built (as robosuite does)."""
    run_dir = tmp_path / "run"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pipeline.cli",
            "run",
            "conf/smoke.yaml",
            "--out",
            str(run_dir),
            "env.suite=tests.doubles.envs:ChattyMarkerEnv",
            "env.tasks=[reach]",
            "episodes_per_task=2",
            f"tracking.uri=sqlite:///{tmp_path / 'mlflow.db'}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, out
    for noise in ("chatty:", "Token authentication", "Started a local Ray", "MLflow database"):
        assert noise not in out, out
    # what the terminal shows: the plan, the progress and its end, the report, the UI link
    assert "4 episodes = 2 cells (baseline, E) x 1 tasks (reach) x 2 episodes" in out
    assert "episodes 4/4" in out and "# IDR evaluation report" in out
    assert "#/compare-runs?runs=" in out
    logs = run_dir / "logs"
    driver = (logs / "driver.log").read_text()
    assert "Started a local Ray instance" in driver and "episodes 4/4" in driver
    workers = sorted(logs.glob("worker-*.log"))
    assert workers, sorted(p.name for p in logs.iterdir())
    text = "".join(p.read_text() for p in workers)
    for line in ("python stdout line", "library warning", "C-level stderr line"):
        assert text.count(f"chatty: {line}") == len(workers), text
