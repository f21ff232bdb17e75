"""Evaluation during training (training/zoo_evaluator.py): each saved checkpoint evaluated once as
it appears, by a process of its own; resumed without repeating a step; a failure recorded against
its step while the next one is evaluated. The loop is tested with a fake evaluation; a toy member
trained through the launcher shows the figures in MLflow against the training step."""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import pytest

from tests.training.test_zoo import _zoo
from training import zoo_benchmarks
from training import zoo_eval_launch as launch
from training import zoo_eval_layout as lay
from training import zoo_eval_measures as meas
from training import zoo_eval_record as rec
from training import zoo_evaluator as ev


def _checkpoint(run: Path, step: int, whole: bool = True, age_s: float = 10.0) -> Path:
    """A saved step folder as lerobot-train leaves it (``whole``: with the weights), last
    written ``age_s`` ago."""
    folder = run / "checkpoints" / f"{step:06d}"
    model = folder / "pretrained_model"
    model.mkdir(parents=True)
    (model / "config.json").write_text("{}")
    if whole:
        (model / "model.safetensors").write_bytes(b"weights")
    return _age(folder, age_s)


def _age(folder: Path, age_s: float = 10.0) -> Path:
    """``folder`` and everything in it last written ``age_s`` ago."""
    then = time.time() - age_s
    for p in [*folder.rglob("*"), folder]:
        os.utime(p, (then, then))
    return folder


class FakeRun:
    """What the loop tells MLflow, kept in memory."""

    def __init__(self) -> None:
        self.logged: dict[int, dict[str, float]] = {}
        self.errors: dict[int, str] = {}

    def metrics(self, step: int, metrics: dict[str, float]) -> None:
        self.logged[step] = metrics

    def error(self, step: int, message: str) -> None:
        self.errors[step] = message


def _fake(calls: list[int], fail_at: int | None = None):
    def evaluate(step: int, checkpoint: Path) -> dict:
        calls.append(step)
        assert checkpoint.name == "pretrained_model"
        if step == fail_at:
            raise RuntimeError("the policy would not load")
        return {"ran": ["openloop"], "metrics": {"openloop_r_img": step / 100}, "errors": {}}

    return evaluate


def test_checkpoints_are_found_by_step_and_evaluated_only_once_whole(tmp_path) -> None:
    run = tmp_path / "tiny_vla_seed0"
    _checkpoint(run, 2)
    _checkpoint(run, 4, whole=False)
    fresh = _checkpoint(run, 6, age_s=0.0)
    (run / "checkpoints" / "last").symlink_to(fresh)
    assert sorted(lay.saved_checkpoints(run)) == [2, 4, 6]  # not `last`
    states = {s: lay.checkpoint_state(p) for s, p in lay.saved_checkpoints(run).items()}
    assert states == {2: "ready", 4: "incomplete", 6: "writing"}
    assert lay.saved_checkpoints(tmp_path / "none") == {}
    assert ev.member_and_seed(run) == ("tiny_vla", 0)
    assert ev.member_and_seed(tmp_path / "smolvla_seed1_continued") == ("smolvla", 1)


def test_a_failing_evaluation_is_recorded_against_its_step_and_the_next_is_evaluated(
    tmp_path,
) -> None:
    run = tmp_path / "run"
    for step in (2, 3, 4, 6):
        _checkpoint(run, step)
    ledger, tracker, calls = rec.Ledger(run / lay.EVALS), FakeRun(), []
    records = ev.run_loop(run, 2, _fake(calls, fail_at=4), ledger, tracker, poll_s=0)
    assert calls == [2, 4, 6]  # step 3 is not a multiple of --every
    assert [(r["step"], r["status"]) for r in records] == [(2, "ok"), (4, "error"), (6, "ok")]
    failed = next(r for r in ledger.records() if r["step"] == 4)
    assert "RuntimeError: the policy would not load" in failed["error"]
    assert failed["cpu_s"] >= 0 and failed["wall_s"] >= 0
    assert tracker.errors == {4: failed["error"]}
    assert tracker.logged[6]["openloop_r_img"] == 0.06
    assert {"eval_cpu_s", "eval_wall_s"} <= set(tracker.logged[4])
    assert not ledger.current.exists()  # no evaluation under way


def test_a_restarted_evaluator_skips_recorded_steps_and_records_a_killed_one(tmp_path) -> None:
    run = tmp_path / "run"
    for step in (2, 4):
        _checkpoint(run, step)
    ledger, calls = rec.Ledger(run / lay.EVALS), []
    ev.run_loop(run, 2, _fake(calls, fail_at=4), ledger, poll_s=0)
    assert calls == [2, 4]
    # an evaluator killed while it evaluated step 6 leaves its marker behind
    _checkpoint(run, 6)
    _checkpoint(run, 8)
    ledger.begin(6)
    tracker, again = FakeRun(), []
    records = ev.run_loop(run, 2, _fake(again), ledger, tracker, poll_s=0)
    assert again == [8]  # 2 and 4 recorded (4 as an error), 6 recorded as killed
    assert [(r["step"], r["status"]) for r in records] == [(6, "error"), (8, "ok")]
    assert "the evaluator stopped while evaluating step 6" in tracker.errors[6]
    assert [r["step"] for r in ledger.records()] == [2, 4, 6, 8]
    assert ev.run_loop(run, 2, _fake(again), ledger, poll_s=0) == [] and again == [8]


def test_the_loop_follows_training_and_records_a_checkpoint_left_incomplete(tmp_path) -> None:
    run = tmp_path / "run"
    ledger, calls, polls = rec.Ledger(run / lay.EVALS), [], []

    def training(_s: float) -> None:  # each poll: training saves a step, then ends
        polls.append(len(polls))
        if len(polls) == 1:
            _checkpoint(run, 2)
            _checkpoint(run, 4, whole=False)  # cut short
        elif len(polls) == 2:
            ended.append(True)

    ended: list[bool] = []
    records = ev.run_loop(
        run, 2, _fake(calls), ledger, ended=lambda: bool(ended), poll_s=0, sleep=training
    )
    assert calls == [2] and [(r["step"], r["status"]) for r in records] == [
        (2, "ok"),
        (4, "incomplete"),
    ]
    # a resumed training saves step 4 again, whole: it is evaluated then
    (run / "checkpoints" / "000004" / "pretrained_model" / "model.safetensors").write_bytes(b"w")
    _age(run / "checkpoints" / "000004")
    ev.run_loop(run, 2, _fake(calls), ledger, poll_s=0)
    assert calls == [2, 4] and 4 in ledger.done()


def test_bad_evaluation_flags_are_refused_naming_the_flag_and_the_fix(tmp_path) -> None:
    frames = tmp_path / "frames"
    (frames / "meta").mkdir(parents=True)
    info = {"features": {k: {"shape": v} for k, v in zoo_benchmarks.TABLETOP_FEATURES.items()}}
    (frames / "meta" / "info.json").write_text(json.dumps(info))

    def check(**kw):
        settings = dict(
            benchmark="tabletop", every=4, save_freq=2, frames=frames, frames_every=1,
            closed_loop_every=5, closed_loop_episodes=20, tracking_uri=None,
        )  # fmt: skip
        meas.check_eval_settings(**{**settings, **kw})

    check()  # fits
    with pytest.raises(SystemExit, match=r"--eval-every 3: give a positive multiple of the save"):
        check(every=3)
    with pytest.raises(SystemExit, match=r"--eval-every 0"):
        check(every=0)
    with pytest.raises(SystemExit, match=r"--closed-loop-every -1: give 0"):
        check(closed_loop_every=-1)
    with pytest.raises(SystemExit, match=r"--eval-frames .*metaworld_demos --root "):
        check(benchmark="metaworld", frames=tmp_path / "missing")
    with pytest.raises(SystemExit, match=r"does not fit the metaworld members"):
        check(benchmark="metaworld")
    with pytest.raises(SystemExit, match=r"--eval-tracking-uri: .*unknown scheme"):
        check(tracking_uri="ftp://somewhere")
    with pytest.raises(SystemExit, match=r"--closed-loop-set \['episodes_per_tsk=1'\]: the "):
        check(closed_loop_set=("episodes_per_tsk=1",))
    check(closed_loop_set=("episodes_per_tsk=1",), closed_loop_every=0)  # no closed loop


def test_the_closed_loop_cell_is_the_zoo_config_on_the_checkpoint_in_diagnose_mode() -> None:
    cfg, sets = meas.closed_loop_overrides("tabletop_pos", Path("/c/pretrained_model"), 20)
    assert cfg == zoo_benchmarks.ROOT / "conf" / "zoo" / "tabletop.yaml"
    assert "env.params.state_dims=[0,1,2,6,7]" in sets and "episodes_per_task=20" in sets
    assert "backbone.params.path=/c/pretrained_model" in sets
    assert {"grid=[{mode: [diagnose]}]", "executor.kind=inline", "executor.workers=1"} <= set(sets)
    e = meas.Evaluation("tabletop", every=2, frames=Path("f"), evals=Path("e"), closed_loop_every=2)
    assert [s for s in (2, 4, 6, 8) if e.closed_loop_due(s)] == [4, 8]
    assert not meas.Evaluation(
        "tabletop", 2, Path("f"), Path("e"), closed_loop_every=0
    ).closed_loop_due(4)


def test_an_evaluator_that_dies_while_training_runs_is_restarted_a_few_times(tmp_path) -> None:
    run = tmp_path / "run"
    dies = launch.EvaluatorProcess([sys.executable, "-c", "raise SystemExit(9)"], run)
    dies.keep_alive()
    assert dies.proc is None  # no checkpoint yet: lerobot-train must create the run folder
    (run / "checkpoints").mkdir(parents=True)
    dies.keep_alive()
    for _ in range(40):
        dies.proc.wait()
        dies.keep_alive()
        if dies.stopping:
            break
    assert dies.restarts == lay.MAX_RESTARTS and dies.stopping
    assert dies.finish(5) == 9  # not started again after training
    locked = launch.EvaluatorProcess(
        [sys.executable, "-c", f"raise SystemExit({lay.EXIT_LOCKED})"], run
    )
    locked.keep_alive()
    locked.proc.wait()
    locked.keep_alive()
    assert locked.restarts == 0 and locked.stopping


@pytest.mark.sim
@pytest.mark.slow
def test_a_member_trained_with_eval_every_has_its_figures_in_mlflow_at_each_saved_step(
    tmp_path, synthetic_tabletop
) -> None:
    from mlflow.tracking import MlflowClient

    runs = tmp_path / "runs"
    common = [
        "--benchmark", "tabletop", "--dataset", str(synthetic_tabletop), "--runs", str(runs),
        "--steps", "4", "--save-freq", "2", "--eval-every", "2",
        "--eval-frames", str(synthetic_tabletop), "--eval-frames-every", "6",
        "--closed-loop-every", "2", "--closed-loop-episodes", "1",
        # one short episode of a task and of its image-zeroed control
        "--closed-loop-set=env.tasks=[pick_color, pick_color@image_blackout:1]",
        "--closed-loop-set=env.params.max_steps={pick_color: 8}",
    ]  # fmt: skip
    refused = _zoo("train", "tiny_vla", *common, "--eval-every", "3")  # the last one counts
    assert refused.returncode != 0 and "--eval-every 3: give a positive multiple" in refused.stderr
    assert not runs.exists()  # refused before training
    t0 = time.perf_counter()
    out = _zoo("train", "tiny_vla", *common)
    first_s = time.perf_counter() - t0
    run = runs / "tiny_vla_seed0"
    log = (run / "evals" / lay.LOG).read_text() if (run / "evals" / lay.LOG).exists() else ""
    assert out.returncode == 0, out.stderr[-3000:] + log[-3000:]
    records = rec.Ledger(run / "evals").records()
    assert [(r["step"], r["status"]) for r in records] == [(2, "ok"), (4, "ok")], log[-3000:]
    assert records[0]["ran"] == ["openloop"] and records[1]["ran"] == ["openloop", "closedloop"]
    assert (run / "evals" / "step_000004" / "episodes").is_dir()
    assert not (run / "evals" / "step_000002").exists()

    uri = f"sqlite:///{run / 'evals' / 'mlflow.db'}"
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("zoo-training")
    (found,) = client.search_runs([exp.experiment_id])
    run_id = (run / "evals" / lay.RUN_ID_FILE).read_text().strip()
    assert found.info.run_id == run_id and found.info.run_name == "tiny_vla_seed0"
    assert (
        found.data.params["member"] == "tiny_vla" and found.data.params["benchmark"] == "tabletop"
    )
    assert int(found.data.params["frames_count"]) == 2 * 6  # 30 frames: 0, 6, ..., 24, 29
    history = {m.step: m.value for m in client.get_metric_history(run_id, "openloop_r_img")}
    assert sorted(history) == [2, 4] and all(0 <= v <= 1 for v in history.values()), history
    for key in ("openloop_r_img_lo", "openloop_e_img", "openloop_e_prop", "eval_cpu_s"):
        assert [m.step for m in client.get_metric_history(run_id, key)] == [2, 4], key
    success = client.get_metric_history(run_id, "success_diagnose")
    assert [m.step for m in success] == [4] and 0 <= success[0].value <= 1
    assert [m.step for m in client.get_metric_history(run_id, "closedloop_r_img")] == [4]
    lo, hi = (client.get_metric_history(run_id, k)[0].value for k in ("success_lo", "success_hi"))
    assert 0 <= lo <= success[0].value <= hi <= 1
    # training's CPU is recorded apart from the evaluator's
    (session,) = [json.loads(x) for x in (run / "zoo_sessions.jsonl").read_text().splitlines()]
    assert session["rc"] == 0 and session["train_cpu_s"] > 0

    # train again: lerobot resumes at step 4 (nothing left), the evaluator reuses the run and
    # evaluates nothing again
    t0 = time.perf_counter()
    again = _zoo("train", "tiny_vla", *common)
    second_s = time.perf_counter() - t0
    assert again.returncode == 0, again.stderr[-3000:]
    assert "--resume=true" in again.stdout
    assert [r["step"] for r in rec.Ledger(run / "evals").records()] == [2, 4]
    assert len(client.search_runs([exp.experiment_id])) == 1
    assert len(client.get_metric_history(run_id, "openloop_r_img")) == 2
    print(f"first session {first_s:.0f} s, resumed {second_s:.0f} s")


def test_an_interrupted_closed_loop_of_another_code_version_is_set_aside_and_rerun(
    tmp_path, monkeypatch
) -> None:
    """A step's closed loop left by another code version may not be resumed (the runner refuses
    mixing versions); the evaluator keeps it aside and runs the step afresh, while a config the
    runner refuses in a fresh run dir stays that step's error."""
    from pipeline.errors import ConfigError
    from pipeline.rundir import read_run_json, write_run_json

    smoke = zoo_benchmarks.ROOT / "conf" / "smoke.yaml"
    overrides = ["tracking.enabled=false", "executor.kind=inline", "episodes_per_task=1"]
    overrides.append("grid=[{mode: [diagnose]}]")
    monkeypatch.setattr(meas, "closed_loop_overrides", lambda *a, **k: (smoke, list(overrides)))
    evaluation = meas.Evaluation("metaworld", 100, tmp_path / "frames", tmp_path / "evals")
    first = evaluation.closed_loop(500, tmp_path / "ckpt")
    out = tmp_path / "evals" / "step_000500"
    meta = read_run_json(out)
    assert meta is not None and first["closedloop_episodes"] == 2.0
    write_run_json(out, {**meta, "code_version": "v0-elsewhere"})

    again = evaluation.closed_loop(500, tmp_path / "ckpt")
    assert again["closedloop_episodes"] == 2.0
    aside = tmp_path / "evals" / "step_000500.superseded-1"
    assert read_run_json(aside)["code_version"] == "v0-elsewhere"  # kept, not mixed
    assert read_run_json(out)["code_version"] != "v0-elsewhere"

    overrides.append("episodes_per_task=0")
    with pytest.raises(ConfigError, match="episodes_per_task"):
        evaluation.closed_loop(1000, tmp_path / "ckpt")
    assert not (tmp_path / "evals" / "step_001000.superseded-1").exists()
