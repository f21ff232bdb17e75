"""One run, end to end: validate, plan the episodes, schedule, store, report (and track).

Everything that can be checked is checked before any actor starts: the config, the suite and
its task ids, the backbone kind, the executor's resources, and whether RUN_DIR belongs to
this config (resume) or to another one (refused).
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.errors import AllEpisodesFailedError, DiskFullError, RunDirLostError
from pipeline.execution.claim import (
    check_run_dir_intact,
    checkpoint_digest,
    code_version,
    resume_or_claim,
    write_meta,
)
from pipeline.execution.compaction import CompactFinishedCells, compact_run_dir
from pipeline.execution.executors import Executor, make_executor
from pipeline.execution.lock import RunDirLock
from pipeline.execution.preflight import (
    check_cell_budget,
    check_executor,
    check_names,
    check_tracking,
    check_videos,
    select_tasks,
)
from pipeline.execution.progress import Progress
from pipeline.execution.run_log import RUN_LOG
from pipeline.execution.scheduler import RunSummary, Scheduler
from pipeline.execution.signals import critical_section
from pipeline.execution.stages import calibrated_specs, held_out_stage, stage_grids
from pipeline.execution.worker_setup import build_worker_spec, host_hardware, with_policy_token
from pipeline.execution.writer import BatchWriter
from pipeline.planning.checkpoint_fit import fit_config
from pipeline.planning.config import ConfigError, RunConfig
from pipeline.planning.env_runtime import check_env_runtime
from pipeline.planning.plan import RunPlan, planned_numerics
from pipeline.planning.provenance import check_hardware, check_numerics, check_resume
from pipeline.reporting.run_data import load_run
from pipeline.reporting.write import write_report
from pipeline.results.store import RunStore
from pipeline.rundir import (
    CALIBRATION_FILE,
    CONFIG_YAML,
    FIGURES_DIR,
    HELD_OUT_DIR,
    LOGS_DIR,
    MARKERS,
    REPORT_MD,
    RUN_JSON,
    check_run_dir,
    read_run_json,
    update_run_json,
)
from workers.episode.rows import EpisodeResult
from workers.hardware import hardware_class

if TYPE_CHECKING:
    from pipeline.reporting.run_data import RunData
    from pipeline.tracking.tracker import Tracker

log = logging.getLogger("idr_eval.runner")


def plan_run(
    cfg: RunConfig,
    run_dir: str | Path,
    yes: bool = False,
    adopt: bool = False,
    allow_code_change: bool = False,
    allow_numerics_change: bool = False,
) -> RunPlan:
    """Everything checked, nothing started; ``yes`` confirms a grid larger than max_cells."""
    run_dir = check_run_dir(run_dir, cfg.output_root)
    check_tracking(cfg, run_dir)
    check_names(cfg)
    # where the simulator runs (an env server: started once here, version and runtime checked)
    server, server_hello = check_env_runtime(cfg)
    tasks = select_tasks(cfg, server)
    # the checkpoint against the env (config.json only): cameras, sizes, dims; the config the
    # run uses, saved and fingerprinted, has what this settled filled in
    cfg, fit = fit_config(cfg)
    check_cell_budget(cfg, len(tasks), yes=yes)
    check_executor(cfg)
    check_videos(cfg)
    run_id = resume_or_claim(cfg, run_dir, adopt)
    version = code_version()
    checkpoint = checkpoint_digest(cfg, run_dir)
    meta = read_run_json(run_dir)
    numerics = planned_numerics(cfg)
    hardware = host_hardware(cfg)
    if meta is not None:
        check_resume(meta, checkpoint, version, run_dir, allow_code_change)
        check_numerics(meta, numerics, run_dir, allow_numerics_change)
        warning = check_hardware(
            meta, hardware and hardware_class(hardware), run_dir, allow_numerics_change
        )
        if warning:
            log.warning(warning)
    specs, deferred = stage_grids(cfg, run_id, tasks, version)
    held_out, record = held_out_stage(cfg, specs, tasks)
    worker_spec = build_worker_spec(cfg, fit, server, run_dir, tasks)
    return RunPlan(
        cfg, run_dir, run_id, tasks, specs, worker_spec, deferred, version, checkpoint, fit,
        server_hello, numerics, hardware, held_out, record,
    )  # fmt: skip


def run_params(plan: RunPlan) -> dict[str, object]:
    """What a run is, as flat MLflow params (the cell's own params are added per child)."""
    cfg = plan.cfg
    return {
        "backbone": cfg.backbone.kind,
        "backbone_params": json.dumps(cfg.backbone.params, sort_keys=True),
        "replan_steps": cfg.backbone.replan_steps,
        "env_protocol": json.dumps(dict(plan.fit.protocol) if plan.fit else {}, sort_keys=True),
        "suite": cfg.env.suite,
        "env_params": json.dumps(cfg.env.params, sort_keys=True),
        "tasks": ",".join(t.task_id for t in plan.tasks),
        "perturbations": ",".join(cfg.env.perturbations),
        "max_steps": json.dumps({t.task_id: t.max_steps for t in plan.tasks}),
        "episodes_per_task": cfg.episodes_per_task,
        "seed": cfg.seed,
        "executor": cfg.executor.kind,
        "workers": cfg.executor.workers,
        "fingerprint": cfg.fingerprint(),
        "code_version": plan.code_version or code_version(),
    }


def execute(plan: RunPlan) -> RunSummary:
    """Run the plan: schedule the episodes not yet stored, write the report, track in MLflow.

    The run directory is locked for the whole run (pipeline.execution.lock) before anything else: a
    second driver on it is refused before it starts Ray or touches a file."""
    with RunDirLock(plan.run_dir):
        return _execute(_after_lock(plan))


def _after_lock(plan: RunPlan) -> RunPlan:
    """The plan, with the run id of a driver that claimed the directory between planning and
    locking (it held the lock then; its run is resumed, under its id)."""
    if not (plan.run_dir / RUN_JSON).is_file():
        return plan
    run_id = resume_or_claim(plan.cfg, plan.run_dir)
    if run_id == plan.run_id:
        return plan
    log.info("%s was claimed by run %s meanwhile: resuming it", plan.run_dir, run_id)
    return replace(
        plan,
        run_id=run_id,
        specs=plan.specs.replace(run_id=run_id),
        calibrated=plan.calibrated.replace(run_id=run_id),
        held_out=plan.held_out.replace(run_id=run_id) if plan.held_out is not None else None,
    )


def _execute(plan: RunPlan) -> RunSummary:
    cfg = plan.cfg
    if cfg.executor.kind == "ray":
        # before anything is written: an unreachable cluster, or one that cannot hold the
        # actors (too few GPUs, a custom resource no node has), is one clear error
        from pipeline.execution.cluster import connect

        connect(cfg.executor)
    write_meta(plan)
    plan = with_policy_token(plan)
    (plan.run_dir / LOGS_DIR).mkdir(exist_ok=True)  # the actors' output (workers.worker_log)
    RUN_LOG.attach(plan.run_dir)  # the CLI's log, from now on in RUN_DIR/logs/driver.log
    store = RunStore(plan.run_dir)
    if store.quarantined:  # unreadable batches moved aside on open: said in run.json too
        was = (read_run_json(plan.run_dir) or {}).get("quarantined", [])
        update_run_json(plan.run_dir, quarantined=sorted({*was, *store.quarantined}))
    tracker = _open_tracker(plan)  # before any actor starts: a bad store is refused up front
    total = len(plan.all_specs())
    on_flush = (lambda batch: tracker.progress(len(batch), total)) if tracker else None

    status, no_report, all_failed = "FAILED", "", None
    try:
        summary = run_episodes(plan, store, on_flush=on_flush, tracker=tracker)
        compact_run_dir(store)
        all_failed = every_episode_failed(store, plan.run_dir)
        status = "FAILED" if all_failed else "FINISHED"
    except KeyboardInterrupt:  # SIGINT, or SIGTERM through pipeline.execution.signals
        status = "KILLED"
        raise
    except DiskFullError:
        no_report = "the disk is full"
        raise
    except RunDirLostError:
        no_report = "the run dir lost its files"
        raise
    finally:
        with critical_section():  # a signal now waits until the report and MLflow are done
            _report_and_track(plan, store, tracker, status, no_report)
    if all_failed:
        raise AllEpisodesFailedError(all_failed)
    return summary


def _read_once(run_dir: Path) -> RunData | None:
    """The run's tables for every view of it; None (each view reads for itself, and the one
    that cannot says so) when they cannot be read together."""
    try:
        return load_run(run_dir)
    except Exception as e:
        log.warning("reading the run once for its views failed: %s: %s", type(e).__name__, e)
        return None


def _open_tracker(plan: RunPlan) -> Tracker | None:
    """The run's MLflow runs, opened (and on resume reopened) before any actor starts."""
    from pipeline.tracking.backend import resolve_uri
    from pipeline.tracking.tracker import Tracker

    cfg = plan.cfg
    if not cfg.tracking.enabled:
        return None
    uri = resolve_uri(cfg.tracking.uri, plan.run_dir)
    try:
        tracker = Tracker(
            uri,
            cfg.tracking.experiment,
            plan.run_dir,
            reconnect_wait_s=cfg.tracking.reconnect_wait_s,
        )
    except RuntimeError as e:
        raise ConfigError(f"tracking.uri: {e}; fix the URI or set tracking.enabled=false") from None
    run_name = f"{cfg.name}-{plan.run_id}"
    tracker.start(run_name=run_name, run_id=plan.run_id, params=run_params(plan), cells=cfg.cells())
    return tracker


def _report_and_track(
    plan: RunPlan, store: RunStore, tracker: Tracker | None, status: str, no_report: str
) -> None:
    """The end of a run, however it ended: the report (unless writing it would fail too:
    `idr-eval report RUN_DIR` rebuilds it later), then the MLflow runs marked ``status``."""
    report = plan.run_dir / REPORT_MD
    data = None
    try:
        if no_report:
            log.error("report not written: %s", no_report)
        else:  # the store read once: the same tables for the report, figures, slices, MLflow
            data = _read_once(plan.run_dir)
            report = write_report(plan.run_dir, data=data)
    except Exception as e:
        _after_stop(status, "writing the report", e)
    if tracker is None:
        return
    try:
        episodes = data.episodes if data is not None else store.episodes().to_pandas()
        figures = sorted((plan.run_dir / FIGURES_DIR).glob("*.png"))
        extra = [plan.run_dir / CONFIG_YAML, plan.run_dir / CALIBRATION_FILE]
        page = report.with_suffix(".html")
        tracker.finish(episodes, [report, page, *extra, *figures], status, data=data)
    except Exception as e:
        _after_stop(status, f"marking the MLflow runs {status}", e)


def every_episode_failed(store: RunStore, run_dir: Path) -> str | None:
    """What to tell the user when every stored episode of the run is an error row (a run that
    measured nothing is a failed run); None when at least one episode ran to its end."""
    errors = store.episodes(columns=["error"]).column("error").to_pylist()
    if not errors or any(e is None for e in errors):
        return None
    causes: dict[str, int] = {}
    for e in errors:
        first = e.splitlines()[0] if e else "(no message)"
        causes[first] = causes.get(first, 0) + 1
    ranked = sorted(causes.items(), key=lambda kv: -kv[1])
    shown = "; ".join(f"{n} x {cause}" for cause, n in ranked[:3])
    return (
        f"every one of the {len(errors)} episodes failed with an error, so this run measured "
        f"nothing: {shown}. Error rows count as stored: fix the cause, then run again with a "
        f"new --out (or delete {run_dir}). report.md lists the errors"
    )


def run_episodes(
    plan: RunPlan,
    store: RunStore | None = None,
    *,
    on_flush: Callable[[list[EpisodeResult]], None] | None = None,
    tracker: Tracker | None = None,
    executor: Executor | None = None,
) -> RunSummary:
    """The run's stages on one executor: the plan's episodes, then, once they are stored,
    tau calibration and the calibrated cells. Episodes already stored are skipped (resume).
    ``executor``: one made by the caller (tests watch its workers); closed here either way."""
    ex = plan.cfg.executor
    store = store if store is not None else RunStore(plan.run_dir)
    executor = executor if executor is not None else make_executor(plan.worker_spec, ex)
    per_task: dict[str, int] = {}  # episodes per task, for the ETA (no spec is built)
    stages = (plan.specs, plan.calibrated, *([plan.held_out] if plan.held_out else []))
    for grid in stages:
        for task in grid.tasks:
            n = len(grid.cells) * grid.episodes_per_task
            per_task[task.task_id] = per_task.get(task.task_id, 0) + n
    total = len(plan.all_specs()) + plan.held_out_count()
    progress = Progress(total, per_task, ex.workers * ex.episodes_per_actor())
    # what the run dir holds now must still be there at each flush
    markers = tuple(n for n in MARKERS if (plan.run_dir / n).exists())
    stored = store.stored_keys()
    cells = [c.cell_id for c in (*plan.specs.cells, *plan.calibrated.cells)]
    per_cell = len(plan.tasks) * plan.cfg.episodes_per_task
    writer = BatchWriter(
        store,
        ex.flush_every,
        on_flush=CompactFinishedCells(cells, per_cell, store, stored, then=on_flush),
        check_dir=lambda: check_run_dir_intact(plan.run_dir, markers),
        stored_keys=stored,
    )
    sched = Scheduler(executor, writer, ex.max_attempts, total=total, progress=progress)
    try:
        sched.run_stage(plan.specs)
        fit_store = store
        if plan.held_out is not None:  # the diagnose cells on their own held-out episodes
            fit_store = RunStore(plan.run_dir / HELD_OUT_DIR)
            held_writer = BatchWriter(
                fit_store,
                ex.flush_every,
                check_dir=lambda: check_run_dir_intact(plan.run_dir, markers),
            )
            sched.run_stage(plan.held_out, writer=held_writer)
            compact_run_dir(fit_store)
        if plan.calibrated:
            sched.run_stage(calibrated_specs(plan, fit_store, tracker))
    finally:
        executor.close()
        progress.close()
    return sched.summary


def _after_stop(status: str, what: str, exc: Exception) -> None:
    """A failure while closing a run: raised after a finished run; after a stopped one only
    logged, so that it does not hide the error (or signal) that stopped the run."""
    if status == "FINISHED":
        raise exc
    log.error("%s failed after the run stopped: %s: %s", what, type(exc).__name__, exc)
