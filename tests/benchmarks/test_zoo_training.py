"""benchmarks/zoo_training.py gathers the evaluator's ledgers into one results file and figure:
steps in order, each figure inside its interval, a failed step kept as its error (never a
number), the figure a PNG of the declared size, and the docs renderer showing every step.

The ledgers here are fabricated test inputs in the evaluator's record format
(``training.zoo_evaluator.evaluate_step`` / ``record_failure``), not measurements."""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import pytest

from tests.benchmarks import load_script

ROOT = Path(__file__).resolve().parents[2]


zoo_training = load_script(ROOT / "benchmarks" / "zoo_training.py")


def _ok(step: int, r: float, success: float | None = None) -> dict[str, Any]:
    """A fabricated ledger line of a step that was evaluated (closed loop where success)."""
    metrics = {
        "openloop_r_img": r,
        "openloop_r_img_lo": r - 0.02,
        "openloop_r_img_hi": r + 0.03,
        "openloop_e_img": r,
        "openloop_e_prop": 1 - r,
    }
    ran = ["openloop"]
    if success is not None:
        ran.append("closedloop")
        metrics |= {
            "success_diagnose": success,
            "success_lo": max(0.0, success - 0.1),
            "success_hi": min(1.0, success + 0.1),
            "closedloop_episodes": 100.0,
            "closedloop_errors": 0.0,
            "closedloop_r_img": r + 0.01,
            "closedloop_r_img_lo": r - 0.01,
            "closedloop_r_img_hi": r + 0.04,
        }
    return {"step": step, "status": "ok", "ran": ran, "metrics": metrics, "cpu_s": 40.5,
            "wall_s": 60.0, "checkpoint": f"RUN/checkpoints/{step:06d}/pretrained_model"}  # fmt: skip


def _run(runs: Path, name: str, lines: list[dict[str, Any]]) -> Path:
    """A run folder with its ledger (written out of step order) and a saved checkpoint."""
    run = runs / name
    (run / "evals").mkdir(parents=True)
    text = "".join(json.dumps(x) + "\n" for x in lines) + '{"step": 9'  # a line cut by a crash
    (run / "evals" / "evals.jsonl").write_text(text)
    model = run / "checkpoints" / "001500" / "pretrained_model"
    model.mkdir(parents=True)
    (model / "train_config.json").write_text(json.dumps({"steps": 3000, "batch_size": 64,
                                                         "seed": 1, "save_freq": 500}))  # fmt: skip
    return run


@pytest.fixture
def data(tmp_path: Path) -> dict[str, Any]:
    failed_closed = _ok(1000, 0.3) | {
        "status": "error",
        "ran": ["openloop", "closedloop"],
        "error": "closedloop: RuntimeError: env died",
    }
    killed = {
        "step": 2000,
        "status": "error",
        "ran": [],
        "metrics": {},
        "error": "the evaluator stopped while evaluating step 2000",
    }
    lines = [_ok(1500, 0.4, 0.8), _ok(500, 0.1, 0.5), failed_closed, killed]
    seed1 = _run(tmp_path, "tiny_vla_seed1", lines)
    seed2 = _run(tmp_path, "tiny_vla_seed2", [_ok(500, 0.2, 0.4), _ok(1000, 0.35, 0.6)])
    return zoo_training.collect([seed1, seed2], [], "metaworld", "python benchmarks/...")


def test_the_results_keep_every_step_in_order_with_its_intervals(data: dict[str, Any]) -> None:
    assert data["machine"]["cpu_model"] and data["date"]
    run = data["runs"]["tiny_vla@seed1"]
    assert (run["member"], run["seed"]) == ("tiny_vla", 1)
    assert [s["step"] for s in run["steps"]] == [500, 1000, 1500, 2000]
    assert run["train"]["steps"] == 3000 and run["train"]["last_saved_step"] == 1500
    assert run["train"]["ended"] is False
    for s in run["steps"]:
        if s["openloop"]:
            lo, hi = s["openloop"]["ci95"]
            assert lo <= s["openloop"]["r_img"] <= hi
        if s["closedloop"]:
            c = s["closedloop"]
            assert c["wilson95"][0] <= c["success"] <= c["wilson95"][1]
            assert c["successes"] == round(c["success"] * c["n"]) and c["n"] == 100
    assert run["steps"][2]["closedloop"]["successes"] == 80
    assert (run["evaluated"], run["closed_loop_steps"]) == (3, 2)
    assert list(data["runs"]) == ["tiny_vla@seed1", "tiny_vla@seed2"]
    json.dumps(data, allow_nan=False)  # valid JSON: no NaN anywhere


def test_a_failed_step_is_its_error_not_a_number(data: dict[str, Any]) -> None:
    steps = {s["step"]: s for s in data["runs"]["tiny_vla@seed1"]["steps"]}
    part = steps[1000]  # the open loop measured, the closed loop failed
    assert part["status"] == "error" and part["closedloop"] is None
    assert part["openloop"]["r_img"] == pytest.approx(0.3)
    assert "env died" in part["error"]
    whole = steps[2000]
    assert whole["openloop"] is None and whole["closedloop"] is None
    assert "evaluator stopped" in whole["error"]
    assert steps[500]["error"] is None


def test_the_figure_is_a_png_of_the_declared_size(data: dict[str, Any], tmp_path: Path) -> None:
    out = tmp_path / "img" / "curves.png"
    zoo_training.draw(data, out)
    head = out.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000
    w, h = struct.unpack(">II", head[16:24])
    fw, fh = zoo_training.FIGSIZE
    assert (w, h) == (round(fw * zoo_training.DPI), round(fh * zoo_training.DPI))


def test_the_renderer_shows_every_step_and_each_failure(data: dict[str, Any]) -> None:
    hook = load_script(ROOT / "docs" / "hooks" / "results_tables.py")
    text = hook.RENDERERS["zoo_training_metaworld"](data)
    assert text.count("| step |") == 2  # one table per member@seed
    for step in ("| 500 |", "| 1,000 |", "| 1,500 |", "| 2,000 |"):
        assert step in text
    assert "80/100: 80% [70, 90]" in text
    assert "step 2,000 (error): the evaluator stopped" in text
    row = next(
        line for line in text.splitlines() if line.startswith("| 1,000 |") and "error" in line
    )
    assert row.count("error") == 2  # the closed loop's two cells; the open loop has its figure
    assert "machine: " in text


def test_a_dry_run_leaves_the_committed_files_alone(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import tempfile

    run = _run(tmp_path, "tiny_vla_seed3", [_ok(500, 0.2, 0.4)])
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    assert zoo_training.main(["--run", str(run), "--dry"]) == 0
    (written,) = (tmp_path / "tmp").rglob("zoo_training_metaworld.json")
    assert written.with_suffix(".png").is_file()
    assert json.loads(written.read_text())["runs"]["tiny_vla@seed3"]["steps"][0]["step"] == 500


def test_a_shipped_final_comes_from_its_committed_results() -> None:
    key, final = zoo_training.shipped_final("tiny_vla", "metaworld")
    card = json.loads((ROOT / "benchmarks/results/zoo_metaworld.json").read_text())
    assert key == f"tiny_vla@seed{final['seed']}"
    assert final["step"] == card["members"]["tiny_vla"]["train"]["steps"]
    for part, ci, value in (("openloop", "ci95", "r_img"), ("closedloop", "wilson95", "success")):
        lo, hi = final[part][ci]
        assert lo <= final[part][value] <= hi
    with pytest.raises(SystemExit, match="--final no_such_member"):
        zoo_training.shipped_final("no_such_member", "metaworld")


def test_merge_keeps_the_runs_held_and_replaces_those_given(tmp_path: Path) -> None:
    """A member trained on another machine joins the file: the runs it held stay with the
    machine and command they were gathered with; a run given again is replaced."""
    out, figure = tmp_path / "zoo_training_metaworld.json", tmp_path / "fig.png"
    held = zoo_training.collect(
        [_run(tmp_path / "a", "tiny_vla_seed1", [_ok(500, 0.1, 0.5)]),
         _run(tmp_path / "a", "tiny_vla_seed2", [_ok(500, 0.2, 0.4)])],
        [], "metaworld", "python benchmarks/zoo_training.py --run A",
    )  # fmt: skip
    for entry in held["runs"].values():  # a file written before runs named their machine
        del entry["machine"], entry["command"]
    held["machine"] = {"cpu_model": "Elsewhere CPU", "cpu_capability": "AVX512"}
    out.write_text(json.dumps(held))
    act = _run(tmp_path / "b", "act_seed0", [_ok(400, 0.3, 0.7)])
    again = _run(tmp_path / "b", "tiny_vla_seed2", [_ok(500, 0.25, 0.45), _ok(1000, 0.3)])
    args = ["--run", str(act), "--run", str(again), "--out", str(out), "--figure", str(figure)]
    assert zoo_training.main([*args, "--merge"]) == 0
    merged = json.loads(out.read_text())
    assert sorted(merged["runs"]) == ["act@seed0", "tiny_vla@seed1", "tiny_vla@seed2"]
    kept = merged["runs"]["tiny_vla@seed1"]
    assert kept["machine"]["cpu_model"] == "Elsewhere CPU" and kept["command"].endswith("--run A")
    assert [s["step"] for s in merged["runs"]["tiny_vla@seed2"]["steps"]] == [500, 1000]
    assert merged["runs"]["act@seed0"]["machine"] == merged["machine"] != held["machine"]
    assert merged["command"].endswith("--merge")
    rendered = load_script(ROOT / "docs" / "hooks" / "results_tables.py").RENDERERS[
        "zoo_training_metaworld"
    ](merged)
    assert "gathered on Elsewhere CPU" in rendered and "**act, seed 0**" in rendered
    # without --merge the file holds the runs given, only
    assert zoo_training.main(args) == 0
    assert sorted(json.loads(out.read_text())["runs"]) == ["act@seed0", "tiny_vla@seed2"]
