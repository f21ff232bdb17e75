"""Evaluation during training: every checkpoint ``lerobot-train`` saves, measured as it appears by
a process of its own, so training never waits for an evaluation.

    python -m training.zoo train tiny_vla --eval-every 1000          # training + its evaluator
    python -m training.zoo_evaluator data/zoo/runs/tiny_vla_seed0 --benchmark tabletop --every 1000

For each saved checkpoint whose step is a multiple of ``--every``:

- open-loop reliance (``pipeline.reporting.reliance``) on the benchmark's held-out demonstration
  frames, read once per evaluator process: R_img with its 95% interval (episodes resampled),
  mean E_img and E_prop;
- at every ``--closed-loop-every``-th of them (steps that are multiples of every x k), a
  closed-loop diagnose cell on the benchmark's zoo config (``pipeline.api.evaluate``, inline,
  one worker: training holds the other core) into ``RUN/evals/step_<step>/``: success with its
  Wilson interval and the cell's R_img, both without the image-zeroed control's episodes (its
  success is logged apart as ``success_control``).

Everything goes to ``RUN/evals/evals.jsonl`` (one line per evaluated step; the resume record) and
to one MLflow run per member x seed (experiment ``zoo-training``) as metrics against the training
step. A step is evaluated once: a restarted evaluator reuses the MLflow run
(``RUN/evals/mlflow_run_id``) and skips the steps recorded. An evaluation that raises, a
checkpoint that never completes and an evaluator killed mid-evaluation (``RUN/evals/current.json``
is left behind) are recorded as errors against their step, and the next checkpoint is evaluated;
a stop by SIGTERM / SIGINT records nothing, so the step is evaluated by the next evaluator.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import signal
import sys
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from training.zoo_benchmarks import BENCHMARKS
from training.zoo_eval_layout import (
    ENDED,
    EVALS,
    EXIT_LOCKED,
    EXPERIMENT,
    HELDOUT,
    LOCK,
    LOG,
    STABLE_S,
    EvaluateFn,
    checkpoint_state,
    log,
    saved_checkpoints,
)
from training.zoo_eval_measures import Evaluation, check_eval_settings, cpu_seconds, describe
from training.zoo_eval_record import Ledger, TrainingRun

if TYPE_CHECKING:
    pass


# --- the loop --------------------------------------------------------------------------------


def evaluate_step(
    step: int,
    checkpoint: Path,
    evaluate: EvaluateFn,
    ledger: Ledger,
    tracker: TrainingRun | None,
) -> dict[str, Any]:
    """Evaluate one checkpoint, record it (evals.jsonl, then MLflow) and return its record. An
    exception is recorded as the step's error; a stop (KeyboardInterrupt) records nothing."""
    log(f"step {step}: evaluating {checkpoint}")
    prepare = getattr(evaluate, "prepare", None)
    if prepare is not None:  # what an evaluator reads once, outside the step's timing
        prepare()
    ledger.begin(step)
    cpu0, t0 = cpu_seconds(), time.perf_counter()
    try:
        try:
            out = evaluate(step, checkpoint)
        except Exception as e:
            log(traceback.format_exc())
            out = {"ran": [], "metrics": {}, "errors": {"evaluation": describe(e)}}
        cpu_s, wall_s = cpu_seconds() - cpu0, time.perf_counter() - t0
        errors = out.get("errors") or {}
        record = {
            "step": step,
            "status": "error" if errors else "ok",
            "ran": out.get("ran", []),
            "metrics": out.get("metrics", {}),
            **({"error": "; ".join(f"{k}: {v}" for k, v in errors.items())} if errors else {}),
            "cpu_s": round(cpu_s, 2),
            "wall_s": round(wall_s, 2),
            "checkpoint": str(checkpoint),
        }
        ledger.append(record)
    finally:
        ledger.end()
    log(f"step {step}: {record['status']} {json.dumps(record['metrics'], default=float)}")
    if tracker is not None:
        tracker.metrics(step, {**record["metrics"], "eval_cpu_s": cpu_s, "eval_wall_s": wall_s})
        if errors:
            tracker.error(step, record["error"])
    return record


def record_failure(
    step: int, status: str, message: str, ledger: Ledger, tracker: TrainingRun | None
) -> dict[str, Any]:
    """A step that could not be evaluated (``status`` error or incomplete), with why."""
    log(f"step {step}: {status}: {message}")
    record = {"step": step, "status": status, "ran": [], "metrics": {}, "error": message}
    ledger.append(record)
    if tracker is not None:
        tracker.error(step, message)
    return record


def run_loop(
    run: Path,
    every: int,
    evaluate: EvaluateFn,
    ledger: Ledger,
    tracker: TrainingRun | None = None,
    *,
    ended: Callable[[], bool] = lambda: True,
    poll_s: float = 2.0,
    stable_s: float = STABLE_S,
    sleep: Callable[[float], None] = time.sleep,
) -> list[dict[str, Any]]:
    """Evaluate each checkpoint due (step a multiple of ``every``, not recorded yet) once it is
    whole, lowest step first; return the new records once ``ended()`` and nothing due is left.
    A checkpoint still incomplete when training has ended is recorded so."""
    new: list[dict[str, Any]] = []
    interrupted = ledger.interrupted_step()
    if interrupted is not None:  # the evaluator before this one was killed evaluating it
        new.append(
            record_failure(
                interrupted,
                "error",
                f"the evaluator stopped while evaluating step {interrupted} (killed or crashed;"
                f" see {ledger.evals / LOG})",
                ledger,
                tracker,
            )
        )
        ledger.end()
    given_up: set[int] = set()
    while True:
        finished = ended()  # read before the scan: what was saved before the end is seen in it
        done = ledger.done() | given_up
        due = {s: p for s, p in sorted(saved_checkpoints(run).items()) if s % every == 0}
        states = {s: checkpoint_state(p, stable_s) for s, p in due.items() if s not in done}
        ready = [s for s, state in states.items() if state == "ready"]
        if ready:
            new.append(evaluate_step(ready[0], due[ready[0]] / "pretrained_model", evaluate,
                                     ledger, tracker))  # fmt: skip
            continue
        if finished:
            for s, state in states.items():
                if state == "incomplete":
                    new.append(
                        record_failure(
                            s,
                            "incomplete",
                            f"checkpoint {due[s]} lacks pretrained_model/config.json or "
                            "model.safetensors and training has ended",
                            ledger,
                            tracker,
                        )
                    )
                    given_up.add(s)
            if all(state == "incomplete" for state in states.values()):
                return new
        sleep(poll_s)


# --- the process -----------------------------------------------------------------------------


def member_and_seed(run: Path) -> tuple[str, int | None]:
    """``NAME_seedS[_continued]`` -> (NAME, S); another name is the member, seed unknown."""
    m = re.fullmatch(r"(.+)_seed(\d+)(_continued)?", run.name)
    return (m.group(1), int(m.group(2))) if m else (run.name, None)


def default_uri(run: Path) -> str:
    return f"sqlite:///{(run / EVALS / 'mlflow.db').resolve()}"


def _stop(signum: int, _frame: Any) -> None:
    raise KeyboardInterrupt(signum)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, help="a zoo run folder (lerobot-train's --output_dir)")
    ap.add_argument("--benchmark", choices=sorted(BENCHMARKS), default="tabletop")
    ap.add_argument("--every", type=int, required=True, help="evaluate steps that are multiples")
    ap.add_argument("--frames", type=Path, default=None, help="default: the benchmark's held-out")
    ap.add_argument("--frames-every", type=int, default=1)
    ap.add_argument("--closed-loop-every", type=int, default=5)
    ap.add_argument("--closed-loop-episodes", type=int, default=20)
    ap.add_argument("--closed-loop-set", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--tracking-uri", default=None, help="default: sqlite:///RUN/evals/mlflow.db")
    ap.add_argument("--member", default=None, help="default: from the run folder's name")
    ap.add_argument("--seed", type=int, default=None)
    ap.add_argument("--device", default="cpu", help="the closed-loop cell's policy device")
    ap.add_argument(
        "--follow",
        action="store_true",
        help="wait for checkpoints until RUN/evals/training_ended appears (`zoo train` writes "
        "it) or the parent process is gone; without it: evaluate what is saved and exit",
    )
    ap.add_argument("--parent-pid", type=int, default=None)
    return ap


def _open_tracker(
    args: argparse.Namespace,
    run: Path,
    evals: Path,
    member: str,
    seed: int | None,
    frames: Path,
    evaluation: Evaluation,
) -> TrainingRun | None:
    """The member x seed's MLflow run (reused by a restarted evaluator), its params logged;
    None where the store is not usable (the figures then go to evals.jsonl only)."""
    tracker = None
    uri = args.tracking_uri or default_uri(run)
    name = member if seed is None else f"{member}_seed{seed}"
    name += "_continued" if run.name.endswith("_continued") else ""  # a stage's own run
    try:
        tracker = TrainingRun(uri, evals, name)
        log(f"MLflow run {tracker.run_id} in {uri} (experiment {EXPERIMENT})")
    except Exception as e:
        log(f"MLflow store {uri} is not usable ({describe(e)}): figures go to evals.jsonl only")
    params: dict[str, Any] = {
        "member": member,
        "seed": seed,
        "benchmark": args.benchmark,
        "frames": str(frames),
        "frames_every": args.frames_every,
        "eval_every": args.every,
        "closed_loop_every": args.closed_loop_every,
        "closed_loop_episodes": args.closed_loop_episodes,
    }
    if tracker is not None:
        tracker.params(params)
        evaluation.on_frames = lambda fs: tracker.params({"frames_count": fs.n})
    return tracker


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    check_eval_settings(
        args.benchmark, args.every, None, args.frames or HELDOUT[args.benchmark][0],
        args.frames_every, args.closed_loop_every, args.closed_loop_episodes,
        args.tracking_uri, flag="", closed_loop_set=tuple(args.closed_loop_set),
    )  # fmt: skip

    # MuJoCo reads its GL backend at its first import (lerobot imports it): the closed-loop cell
    # runs inline in this process
    from workers.rendering import configure_rendering

    configure_rendering()
    logging.basicConfig(level=logging.INFO, stream=sys.stdout, format="%(message)s")
    signal.signal(signal.SIGTERM, _stop)
    run = args.run.resolve()
    evals = run / EVALS
    evals.mkdir(parents=True, exist_ok=True)
    from filelock import FileLock, Timeout

    lock = FileLock(str(evals / LOCK))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        log(f"another evaluator is evaluating {run} ({evals / LOCK} is held): not starting")
        return EXIT_LOCKED
    member, seed = member_and_seed(run)
    member, seed = args.member or member, args.seed if args.seed is not None else seed
    frames = (args.frames or HELDOUT[args.benchmark][0]).resolve()
    evaluation = Evaluation(
        benchmark=args.benchmark,
        every=args.every,
        frames=frames,
        evals=evals,
        frames_every=args.frames_every,
        closed_loop_every=args.closed_loop_every,
        closed_loop_episodes=args.closed_loop_episodes,
        closed_loop_set=tuple(args.closed_loop_set),
        device=args.device,
    )
    tracker = _open_tracker(args, run, evals, member, seed, frames, evaluation)
    ended_file, parent = evals / ENDED, args.parent_pid

    def ended() -> bool:
        return (
            not args.follow
            or ended_file.exists()
            or (parent is not None and os.getppid() != parent)
        )

    status = "FAILED"
    try:
        records = run_loop(run, args.every, evaluation, Ledger(evals), tracker, ended=ended)
        status = "FINISHED"
        log(f"done: {len(records)} steps recorded in this session")
        return 0
    except KeyboardInterrupt as e:
        status = "KILLED"
        signum = getattr(e, "signum", None) or (
            e.args[0] if e.args and isinstance(e.args[0], int) else signal.SIGINT
        )
        log(f"stopped by {signal.Signals(signum).name}: the step under way is evaluated next time")
        return 128 + signum
    finally:
        if tracker is not None:
            tracker.close(status)
        lock.release()


if __name__ == "__main__":
    raise SystemExit(main())
