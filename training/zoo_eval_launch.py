"""The evaluator as ``python -m training.zoo train --eval-every N`` runs it: its flags and
their refusals before training starts, and the evaluator process beside lerobot-train
(started once the run folder exists, restarted if it dies, given a bounded wait at the end).
"""

from __future__ import annotations

import argparse
import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

from training.zoo_benchmarks import ROOT, offline_env
from training.zoo_eval_layout import ENDED, EVALS, EXIT_LOCKED, HELDOUT, LOG, MAX_RESTARTS
from training.zoo_eval_measures import check_eval_settings

if TYPE_CHECKING:
    pass


# --- for `zoo train` -------------------------------------------------------------------------


def add_train_flags(p: argparse.ArgumentParser) -> None:
    """``zoo train``'s flags of the evaluation during training."""
    g = p.add_argument_group("evaluation during training (training/zoo_evaluator.py)")
    g.add_argument(
        "--eval-every",
        type=int,
        default=None,
        help="evaluate each saved checkpoint whose step is a multiple of N (a multiple of the "
        "save frequency), in a process of its own while training runs",
    )
    g.add_argument(
        "--eval-frames",
        type=Path,
        default=None,
        help="held-out demonstrations for the open-loop reliance (default "
        "data/zoo/<benchmark>_heldout)",
    )
    g.add_argument("--eval-frames-every", type=int, default=1, help="every K-th frame")
    g.add_argument(
        "--closed-loop-every",
        type=int,
        default=5,
        help="a closed-loop diagnose cell at every k-th evaluated checkpoint (0: never)",
    )
    g.add_argument("--closed-loop-episodes", type=int, default=20, help="episodes per task")
    g.add_argument(
        "--closed-loop-set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="an override of the closed-loop cell's config (repeat), e.g. 'env.tasks=[pick_color]'",
    )
    g.add_argument(
        "--eval-tracking-uri",
        default=None,
        help="the MLflow store (default sqlite:///RUN/evals/mlflow.db); experiment zoo-training",
    )
    g.add_argument(
        "--eval-final-wait-s",
        type=float,
        default=1800.0,
        help="after training, how long the evaluator may take for the checkpoints already saved",
    )


def check_train_flags(args: argparse.Namespace, save_freq: int) -> None:
    """`zoo train --eval-every`'s refusals, before training starts."""
    if args.eval_frames is None:
        args.eval_frames = HELDOUT[args.benchmark][0]
    check_eval_settings(
        args.benchmark, args.eval_every, save_freq, args.eval_frames, args.eval_frames_every,
        args.closed_loop_every, args.closed_loop_episodes, args.eval_tracking_uri,
        closed_loop_set=tuple(args.closed_loop_set),
    )  # fmt: skip


def children_cpu_s() -> float:
    """CPU seconds of this process's waited-for children."""
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


class EvaluatorProcess:
    """The evaluator beside a `zoo train`: started once ``RUN/checkpoints`` exists (lerobot-train
    refuses an output folder that exists before it starts a fresh run), restarted when it dies
    while training runs (at most ``MAX_RESTARTS`` times), told when training has ended, and
    stopped after a bounded wait. Its output goes to ``RUN/evals/evaluator.log``."""

    def __init__(self, command: list[str], run: Path, threads: int = 1) -> None:
        self.command = command
        self.run = run
        self.threads = threads
        self.proc: subprocess.Popen | None = None
        self.restarts = 0
        self.stopping = False
        self.reaped_cpu_s = 0.0  # CPU of evaluators reaped while training ran (not training's)

    @classmethod
    def for_training(cls, args: argparse.Namespace, run: Path) -> EvaluatorProcess:
        run = run.resolve()
        command = [
            sys.executable, "-m", "training.zoo_evaluator", str(run),
            "--benchmark", args.benchmark,
            "--every", str(args.eval_every),
            "--frames", str(Path(args.eval_frames).resolve()),
            "--frames-every", str(args.eval_frames_every),
            "--closed-loop-every", str(args.closed_loop_every),
            "--closed-loop-episodes", str(args.closed_loop_episodes),
            *(f"--closed-loop-set={s}" for s in args.closed_loop_set),
            *(["--tracking-uri", args.eval_tracking_uri] if args.eval_tracking_uri else []),
            "--member", args.name,
            "--seed", str(args.seed),
            "--device", args.device,
            "--follow",
            "--parent-pid", str(os.getpid()),
        ]  # fmt: skip
        return cls(command, run)

    def start(self) -> None:
        evals = self.run / EVALS
        evals.mkdir(parents=True, exist_ok=True)
        (evals / ENDED).unlink(missing_ok=True)
        with (evals / LOG).open("a") as out:
            # a session of its own: a Ctrl-C reaches it through `zoo train` (which stops it), not
            # straight from the terminal while it writes its record
            self.proc = subprocess.Popen(
                self.command,
                cwd=ROOT,
                env=offline_env(self.threads),
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        print(f"evaluator: pid {self.proc.pid}, log in {evals / LOG}", flush=True)

    def keep_alive(self) -> None:
        """Start the evaluator once the run folder has checkpoints; restart one that died."""
        if self.stopping:
            return
        if self.proc is None:
            if (self.run / "checkpoints").is_dir():
                self.start()
            return
        before = children_cpu_s()
        rc = self.proc.poll()
        if rc is None:
            return
        self.reaped_cpu_s += children_cpu_s() - before
        if rc == EXIT_LOCKED or self.restarts >= MAX_RESTARTS:
            print(
                f"evaluator exited ({rc}); not restarted: see {self.run / EVALS / LOG}", flush=True
            )
            self.stopping = True
            return
        self.restarts += 1
        print(f"evaluator exited ({rc}) while training runs: restarting it", flush=True)
        self.start()

    def stop(self, signum: int = signal.SIGTERM) -> None:
        """Stop now (a stop of `zoo train`): the step under way is evaluated next time."""
        self.stopping = True
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signum)

    def finish(self, wait_s: float) -> int | None:
        """Let the evaluator evaluate what is saved (at most ``wait_s``), then stop it; after a
        stop of `zoo train`, only wait for it to exit."""
        if self.stopping:
            return None if self.proc is None else self._wait_or_kill(60.0)
        if self.proc is None or (self.proc.poll() is not None and self.proc.returncode != 0):
            if not (self.run / "checkpoints").is_dir():
                return None
            # training saved its first checkpoint and ended between two polls, or the evaluator
            # died after the last one: one more, to record that and finish
            self.start()
        assert self.proc is not None
        (self.run / EVALS / ENDED).touch()
        try:
            return self.proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            print(
                f"--eval-final-wait-s {wait_s:g} reached: stopping the evaluator (the checkpoints "
                "not evaluated yet are evaluated by the next `train`)",
                flush=True,
            )
            self.proc.terminate()
            return self._wait_or_kill(60.0)

    def _wait_or_kill(self, wait_s: float) -> int:
        assert self.proc is not None
        try:
            return self.proc.wait(timeout=wait_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait()


def wait_training(
    child: subprocess.Popen, timeout: float | None, evaluator: EvaluatorProcess | None
) -> int:
    """``child.wait(timeout)``, keeping the evaluator alive meanwhile (TimeoutExpired as
    ``Popen.wait``)."""
    if evaluator is None:
        return child.wait(timeout=timeout)
    deadline = None if timeout is None else time.monotonic() + timeout
    while True:
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            raise subprocess.TimeoutExpired(child.args, timeout or 0)
        try:
            return child.wait(timeout=2.0 if left is None else min(2.0, left))
        except subprocess.TimeoutExpired:
            evaluator.keep_alive()
