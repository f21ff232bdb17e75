"""Every CLI failure is one message and a non-zero exit, never a traceback."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline import cli

ROOT = Path(__file__).resolve().parents[2]
SMOKE = str(ROOT / "conf" / "smoke.yaml")
OFF = ["tracking.enabled=false", "executor.kind=inline"]


def _bad_invocations(tmp: Path) -> list[tuple[list[str], int, str]]:
    (tmp / "a_file").write_text("x")
    (tmp / "not_a_run").mkdir()
    return [
        (["run", SMOKE, "--out", "/proc/x", *OFF], 2, "is not writable"),
        (["run", SMOKE, "--out", str(tmp / "a_file"), *OFF], 2, "is an existing file"),
        (["run", str(tmp / "missing.yaml"), "--out", str(tmp / "r")], 2, "not found"),
        (["run", SMOKE, "--out", str(tmp / "r"), "executor.workers"], 2, "unrecognized arguments"),
        (["run", SMOKE, "--out", str(tmp / "r"), "executor.workers==2"], 2, "executor.workers"),
        (
            ["run", SMOKE, "--out", str(tmp / "r"), "env.suite=no.such.module:Env"],
            2,
            "cannot import",
        ),
        (
            [
                "run",
                SMOKE,
                "--out",
                str(tmp / "r"),
                "backbone.kind=lerobot",
                "backbone.params={path: lerobot/pi05_libero}",
            ],
            2,
            "not downloadable here",
        ),
        (["report", str(tmp / "not_a_run")], 2, "is not a run dir"),
        (
            [
                "run",
                SMOKE,
                "--out",
                str(tmp / "r2"),
                *OFF,
                "env.suite=tests.doubles.envs:UnloadableMarkerEnv",
            ],
            1,
            "the worker cannot load: RuntimeError: simulator cannot start",
        ),
    ]


def test_bad_invocations_are_one_message_each(tmp_path, capsys) -> None:
    for argv, code, message in _bad_invocations(tmp_path):
        try:
            got = cli.main(argv)
        except SystemExit as e:  # argparse's own usage error: one line, exit 2
            got = e.code
        err = capsys.readouterr().err
        assert got == code, (argv, got, err)
        assert err.count("idr-eval: error:") == 1 and message in err, (argv, err)
        assert "Traceback" not in err


@pytest.mark.slow
def test_a_worker_that_cannot_load_stops_a_ray_run(tmp_path, ray_local) -> None:
    """Ray: the same constructor error twice stops the run with that error (not after every
    retry, not as a Ray traceback)."""
    from pipeline.errors import RunError
    from pipeline.execution.runner import plan_run, run_episodes
    from pipeline.planning.config import load_config

    cfg = load_config(
        SMOKE,
        [
            "tracking.enabled=false",
            "executor.kind=ray",
            "executor.workers=1",
            "env.suite=tests.doubles.envs:UnloadableMarkerEnv",
        ],
    )
    with pytest.raises(
        RunError, match=r"the workers cannot load: RuntimeError: simulator cannot start"
    ):
        run_episodes(plan_run(cfg, tmp_path / "r"))


def test_a_run_whose_every_episode_fails_exits_non_zero_and_says_so(tmp_path, capsys) -> None:
    """12 episodes, each an error row (NaN from the backbone at every call): a run that measured nothing is a failed
    run (exit 1, one message naming the common error), with its report and rows kept."""
    out = tmp_path / "r"
    calls = ",".join(map(str, range(400)))
    argv = [
        "run",
        SMOKE,
        "--out",
        str(out),
        *OFF,
        "executor.max_attempts=1",
        "backbone.kind=tests.doubles.backbones:FaultyMarkerBackbone",
        f"backbone.params.nonfinite_calls=[{calls}]",
    ]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert err.count("idr-eval: error:") == 1 and "Traceback" not in err
    assert "every one of the 12 episodes failed" in err
    # the baseline cell's and the E cell's, grouped by their first line
    assert "6 x NonFiniteActionError: non-finite action at step 0" in err
    assert "6 x ValueError: " in err
    assert "12 error rows" in (out / "report.md").read_text()
    # one episode that ends is enough for a run to count as done
    argv[-1] = "backbone.params.nonfinite_calls=[0]"
    assert cli.main([*argv[:3], str(tmp_path / "r2"), *argv[4:]]) == 0
