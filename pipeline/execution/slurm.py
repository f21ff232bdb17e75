"""A grid inside a Slurm allocation: Ray across its nodes, the driver on the first, and a clean
stop before Slurm's kill that the job's next start resumes.

    sbatch -N 2 docker/slurm.sbatch conf/grids/alpha.yaml /shared/runs/alpha
    idr-eval slurm CONFIG --out RUN_DIR [key=value ...]      # what the script runs

This follows Ray's Slurm pattern: the head on the allocation's first node (where the batch
script runs), one ``ray start --block`` per other node through ``srun``, and the driver
(``idr-eval run ... executor.address=HEAD:PORT``) on the head. Each Ray node gets the CPUs and
GPUs Slurm gave it on that node, so the allocation's GPUs are what policy actors are placed on.
``ray symmetric-run`` is not used: it ends with ``ray stop`` (every Ray of the user on the node,
another job's included), passes no signal on to its command, and takes no node address.

Before any Ray starts (one message, non-zero exit): outside an allocation (names ``sbatch`` and
``salloc``), controller unreachable (names ``scontrol ping``), an allocation smaller than the
config's actors (both numbers), and a run dir that not every node sees (each node writes a
token beside it through ``srun``; the driver must see them all).

Signals (the batch script asks for ``--requeue --signal=B:USR1@120``):

- USR1, Slurm's warning before the wall-time limit: the driver stops cleanly (results flushed,
  MLflow runs KILLED) and the launcher requeues the job with ``scontrol requeue``; its next
  start resumes the run dir. USR1, not TERM: TERM is also what ``scancel`` sends, so it cannot
  mean "requeue me".
- TERM (``scancel``, ``scontrol requeue``, preemption): the driver stops cleanly. Slurm requeues
  the job itself when it was requeued or preempted; after ``scancel``, submitting the same
  command again resumes.

Here the launcher: the signals, the driver, the stop events and the requeue. What Slurm gave the
job and the checks on it: ``pipeline.execution.slurm_allocation``; Ray's nodes:
``pipeline.execution.slurm_ray``.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from types import FrameType

from pipeline.errors import ConfigError
from pipeline.execution.slurm_allocation import (
    Allocation,
    check_fits,
    check_shared,
    kill_wait_s,
    ping_controller,
    read_allocation,
    scontrol,
    warn_sqlite_on_network_fs,
)
from pipeline.execution.slurm_ray import start_ray

log = logging.getLogger("idr_eval.slurm")
STOP_WAIT_S = 60.0  # for the driver to flush and exit after a stop signal
STOP_MARGIN_S = 5.0  # of Slurm's KillWait kept for the launcher's own stop event and Ray's stop
EVENTS = "slurm.jsonl"  # in the run dir: one line per start and stop of the launcher


def stop_wait_s(kill_wait: float | None) -> float:
    """How long the driver gets for its clean stop: STOP_WAIT_S, cut to end before Slurm's KILL
    would end the launcher too (which would then leave no stop event and no Ray logs)."""
    if kill_wait is None:
        return STOP_WAIT_S
    return max(1.0, min(STOP_WAIT_S, kill_wait - STOP_MARGIN_S))


class _Stop:
    signum: int | None = None
    requeue = False


class EventLog:
    """This start's lines of RUN_DIR/slurm.jsonl, written as they happen once the driver has
    made the run dir (nothing may be written there before): a start Slurm SIGKILLs after its
    KillWait still leaves what it did."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self.pending: list[dict] = []

    def emit(self, event: str, **fields: object) -> None:
        self.pending.append({"t": round(time.time(), 3), "event": event, **fields})
        self.flush()

    def flush(self) -> None:
        from pipeline.rundir import RUN_JSON

        if self.pending and (self.run_dir / RUN_JSON).is_file():
            with (self.run_dir / EVENTS).open("a") as f:
                f.writelines(json.dumps(e) + "\n" for e in self.pending)
            self.pending.clear()


def _keep_ray_logs(run_dir: Path, control: Path, restarts: int) -> None:
    from pipeline.rundir import LOGS_DIR, RUN_JSON

    logs = control / "ray-logs"
    if logs.is_dir() and (run_dir / RUN_JSON).is_file():
        dest = run_dir / LOGS_DIR / f"ray-{control.name.removeprefix('.')}-{restarts}"
        shutil.rmtree(dest, ignore_errors=True)
        shutil.copytree(logs, dest)


def run(config: str, out: str, overrides: list[str], driver_args: list[str]) -> int:
    """Pre-flight, Ray across the allocation, the driver; returns the driver's exit code."""

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        _Stop.signum = signum
        _Stop.requeue = _Stop.requeue or signum == signal.SIGUSR1

    # first of all: USR1's default action would end this process before the driver is told
    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGUSR1, signal.SIGTERM)}
    try:
        return _run(config, out, overrides, driver_args)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _run(config: str, out: str, overrides: list[str], driver_args: list[str]) -> int:
    from pipeline.planning.config import load_config

    if any(o.startswith("executor.address=") for o in overrides):
        raise ConfigError(
            "executor.address is set by `idr-eval slurm` (the head it starts); drop it"
        )
    cfg = load_config(config, overrides)  # a bad config fails here, before Slurm is asked
    if not os.environ.get("SLURM_JOB_ID"):
        read_allocation()  # the message that names sbatch and salloc
    ping_controller()
    alloc = read_allocation()
    here = os.environ.get("SLURMD_NODENAME")
    if here != alloc.nodes[0]:
        # inside salloc the shell is on the login node: the head must be on the allocation
        raise ConfigError(
            f"`idr-eval slurm` runs on the allocation's first node ({alloc.nodes[0]}), this is "
            f"{here or 'not a node of it'}: submit docker/slurm.sbatch with sbatch, or inside "
            f"salloc run `srun --nodes=1 --ntasks=1 --nodelist={alloc.nodes[0]} idr-eval slurm "
            "...`"
        )
    gpus = sum(n * d.get("GPU", 0.0) for _, n, d in cfg.executor.actor_groups())
    check_fits(alloc, cfg.executor.local_cpus(), gpus)
    run_dir = Path(out).resolve()
    control = run_dir.parent / f".slurm-{alloc.job_id}-{run_dir.name}"
    try:
        check_shared(alloc, control, run_dir)
        warn_sqlite_on_network_fs(cfg.tracking.uri, run_dir)
        return _launch(config, run_dir, overrides, driver_args, alloc, control)
    finally:
        shutil.rmtree(control, ignore_errors=True)


def _launch(
    config: str,
    run_dir: Path,
    overrides: list[str],
    driver_args: list[str],
    alloc: Allocation,
    control: Path,
) -> int:
    token = control / "ray_auth_token"
    token.write_text(secrets.token_hex(32))
    token.chmod(0o600)
    # one token for this job's Ray: its nodes, the driver and this launcher's node count
    os.environ.update(
        RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(token), RAY_USAGE_STATS_ENABLED="0"
    )
    os.environ.pop("RAY_AUTH_TOKEN", None)
    os.environ.pop("RAY_ADDRESS", None)
    env = dict(os.environ)
    t0 = time.time()
    events = EventLog(run_dir)
    events.emit(
        "start",
        job=alloc.job_id,
        restarts=alloc.restarts,
        nodes=list(alloc.nodes),
        cpus=list(alloc.cpus),
        gpus=list(alloc.gpus),
    )
    ray = start_ray(alloc, control, env)
    log.info("Ray on %d node(s) at %s in %.1f s", len(alloc.nodes), ray.address, time.time() - t0)
    events.emit("ray_up", address=ray.address)
    rc = 128 + (_Stop.signum or 0)
    killed = False
    try:
        if _Stop.signum is None:  # not stopped while Ray was starting
            wait_s = stop_wait_s(kill_wait_s())
            rc, killed = _drive(
                config, run_dir, overrides, driver_args, ray.address, env, events, wait_s
            )
        requeued = _Stop.requeue and rc != 0
        events.emit(
            "stop",
            rc=rc,
            signal=signal.Signals(_Stop.signum).name if _Stop.signum else None,
            requeued=requeued,
            driver_killed=killed,
        )
    finally:
        ray.stop()
    _keep_ray_logs(run_dir, control, alloc.restarts)
    if requeued:
        # the wall-time warning: back to the queue; the job's next start resumes the run dir
        scontrol("requeue", alloc.job_id)
    return rc


def _drive(
    config: str,
    run_dir: Path,
    overrides: list[str],
    driver_args: list[str],
    address: str,
    env: dict[str, str],
    events: EventLog,
    wait_s: float,
) -> tuple[int, bool]:
    """``idr-eval run`` against this job's Ray; a stop signal becomes its clean stop (TERM),
    and a driver not done after ``wait_s`` is killed. Returns its exit code and whether it was
    killed."""
    cmd = [
        str(Path(sys.executable).with_name("idr-eval")),
        "run",
        config,
        "--out",
        str(run_dir),
        *driver_args,
        *overrides,
        f"executor.address={address}",
    ]
    driver = subprocess.Popen(cmd, env={**env, "RAY_ADDRESS": address})
    stop_deadline: float | None = None
    killed = False
    while True:
        try:
            return driver.wait(timeout=0.5), killed
        except subprocess.TimeoutExpired:
            events.flush()  # once the driver has made the run dir
        if _Stop.signum is not None and stop_deadline is None:
            driver.send_signal(signal.SIGTERM)  # flush, MLflow KILLED, exit 143
            stop_deadline = time.monotonic() + wait_s
        if stop_deadline is not None and time.monotonic() > stop_deadline and not killed:
            log.warning("the driver did not stop within %.0f s of the signal: killing it", wait_s)
            driver.kill()
            killed = True
