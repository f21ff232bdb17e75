"""One run, end to end: validate, plan the episodes, schedule, store, report (and track).

Everything that can be checked is checked before any actor starts: the config, the suite and
its task ids, the backbone kind, the executor's resources, and whether RUN_DIR belongs to
this config (resume) or to another one (refused).
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import uuid
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.errors import AllEpisodesFailedError, DiskFullError, RunDirLostError
from pipeline.execution.executors import Executor, make_executor
from pipeline.execution.lock import RunDirLock
from pipeline.execution.progress import Progress
from pipeline.execution.run_log import RUN_LOG
from pipeline.execution.scheduler import RunSummary, Scheduler
from pipeline.execution.signals import critical_section
from pipeline.execution.writer import BatchWriter
from pipeline.planning.checkpoint_fit import Fit, fit_config
from pipeline.planning.config import ConfigError, RunConfig, dump_config
from pipeline.planning.env_runtime import check_env_runtime
from pipeline.planning.plan import CellPlan, Chain, SpecGrid
from pipeline.planning.provenance import check_resume, checkpoint_path, checkpoint_record
from pipeline.reporting.write import write_report
from pipeline.results.calibration import calibrate
from pipeline.results.store import RunStore
from pipeline.rundir import (
    CALIBRATION_FILE,
    CONFIG_YAML,
    EPISODES_DIR,
    FIGURES_DIR,
    LOCK_FILE,
    LOGS_DIR,
    MARKERS,
    REPORT_MD,
    RUN_JSON,
    check_run_dir,
    read_run_json,
    update_run_json,
    write_run_json,
    write_text_atomic,
)
from workers.backbones.factory import check_backbone
from workers.envs.base import TaskSpec, env_member
from workers.envs.factory import check_suite, env_class, suite_tasks
from workers.envs.server.client import ServerSpec
from workers.episode import EpisodeResult, WorkerSpec

if TYPE_CHECKING:
    from pipeline.tracking.tracker import Tracker

log = logging.getLogger("idr_eval.runner")


def code_version() -> str:
    here = Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(
            ["git", "-C", str(here), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True,
            text=True,
            timeout=5,
            check=True,
        )
        return out.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        from importlib.metadata import version

        return f"idr-eval-{version('idr-eval')}"


@dataclass
class RunPlan:
    cfg: RunConfig
    run_dir: Path
    run_id: str
    tasks: list[TaskSpec]
    specs: SpecGrid  # the first stage (lazy: made when the scheduler reaches them)
    worker_spec: WorkerSpec
    calibrated: SpecGrid  # scheduled after tau calibration, with tau filled in then
    code_version: str = ""
    checkpoint: dict[str, object] | None = None  # pipeline.planning.provenance.checkpoint_record
    fit: Fit | None = None  # what the pre-flight settled (pipeline.planning.checkpoint_fit)
    env_server: dict[str, object] | None = None  # the env server's hello (python, version)

    def all_specs(self) -> Chain:
        return Chain((self.specs, self.calibrated))


def _check_names(cfg: RunConfig) -> None:
    try:
        check_suite(cfg.env.suite, cfg.env.params)
        check_backbone(cfg.backbone.kind, cfg.backbone.params)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def _select_tasks(cfg: RunConfig, server: ServerSpec | None = None) -> list[TaskSpec]:
    """The run's tasks: env.tasks (all of the suite's by default), each crossed with
    env.perturbations unless it names its own (``pick_color@light_dim:0.4``); a perturbation
    the suite cannot apply is refused here, before any work."""
    from workers.envs.wrappers.perturbations import (
        IMAGE_KINDS,
        SEP,
        parse,
        perturbed_task,
        split_task,
    )

    tasks = suite_tasks(cfg.env.suite, cfg.env.params, server)
    by_id = {t.task_id: t for t in tasks}
    crossed = [parse(p) for p in cfg.env.perturbations]
    names = cfg.env.tasks if cfg.env.tasks is not None else list(by_id)
    out: dict[str, TaskSpec] = {}
    unknown = []
    for name in names:
        try:
            base, own = split_task(name)
        except ValueError as e:
            raise ConfigError(f"env.tasks: {name!r}: {e}") from None
        if base not in by_id:
            unknown.append(name)
            continue
        for p in [own] if SEP in name else crossed:
            task = perturbed_task(by_id[base], p)
            out.setdefault(task.task_id, task)
    if unknown:
        raise ConfigError(
            f"env.tasks: {unknown} not in suite {cfg.env.suite!r}; known: {sorted(by_id)}"
        )
    kinds = env_member(env_class(cfg.env.suite), "perturbation_kinds")
    scene = {p.kind for t in out for p in [split_task(t)[1]] if p is not None and p.scene}
    if bad := sorted(scene - set(kinds)):
        can = ", ".join(kinds) if kinds else "no scene perturbation"
        raise ConfigError(
            f"env.perturbations: suite {cfg.env.suite!r} cannot apply {bad} (it applies {can}); "
            f"the image kinds ({', '.join(IMAGE_KINDS)}) work with any suite"
        )
    short = {t.task_id: t.episodes_total for t in out.values() if t.episodes_total is not None}
    if short and cfg.episodes_per_task > (least := min(short.values())):
        fewest = sorted(k for k, v in short.items() if v == least)
        raise ConfigError(
            f"episodes_per_task={cfg.episodes_per_task}: {fewest} have {least} episodes in their "
            f"fixed list; set episodes_per_task <= {least}"
        )
    if (check := env_member(env_class(cfg.env.suite), "check_tasks")) is not None:
        bases = list(dict.fromkeys(split_task(t)[0] for t in out))
        try:
            check(bases, cfg.episodes_per_task, **cfg.env.params)
        except ValueError as e:
            raise ConfigError(str(e)) from None
    return list(out.values())


def _perturbations_of(tasks: list[TaskSpec]) -> tuple[str, ...]:
    """The perturbations the tasks name (``none`` for plain ones); () when none is named, so
    that an unperturbed run's env is not wrapped at all."""
    from workers.envs.wrappers.perturbations import SEP, perturbation_of

    if not any(SEP in t.task_id for t in tasks):
        return ()
    return tuple(dict.fromkeys(perturbation_of(t.task_id) for t in tasks))


def _check_executor(cfg: RunConfig) -> None:
    ex = cfg.executor
    if ex.policy == "shared" and ex.kind != "ray":
        raise ConfigError(
            "executor.policy=shared runs policy actors on Ray: set executor.kind=ray (inline "
            "holds the backbone in this process: executor.policy=in_actor)"
        )
    if ex.kind == "ray" and ex.address is None and not ex.oversubscribe:
        need = ex.local_cpus()
        have = os.cpu_count() or 1
        if need > have:
            policy = (
                f" + executor.policy_actors={ex.policy_actors} x executor.policy_cpus="
                f"{ex.policy_cpus}"
                if ex.policy == "shared"
                else ""
            )
            raise ConfigError(
                f"executor.workers={ex.workers} x executor.cpus_per_worker={ex.cpus_per_worker}"
                f"{policy} needs {need:g} CPUs but this machine has {have}; lower "
                "executor.workers or set executor.oversubscribe=true"
            )


def _resume_or_claim(cfg: RunConfig, run_dir: Path, adopt: bool = False) -> str:
    """Return the run id; refuse a RUN_DIR that holds another config's results. ``adopt``:
    take over a run dir whose run.json was lost but whose config.yaml and data are intact."""
    fingerprint = cfg.fingerprint()
    meta = read_run_json(run_dir)
    if meta is not None:
        if meta.get("fingerprint") != fingerprint:
            raise ConfigError(
                f"{run_dir} holds results of a different config (fingerprint {meta.get('fingerprint')} "
                f"vs {fingerprint}); results of two configs are never mixed. Use a new --out, or "
                f"delete {run_dir} to start fresh"
            )
        return str(meta["run_id"])
    if not (run_dir.exists() and any(p.name != LOCK_FILE for p in run_dir.iterdir())):
        return uuid.uuid4().hex[:12]
    stored = RunStore(run_dir, read_only=True)
    if not (run_dir / EPISODES_DIR).is_dir():
        raise ConfigError(f"{run_dir} exists and is not an idr-eval run dir; choose an empty --out")
    if not adopt:
        raise ConfigError(
            f"{run_dir} has no {RUN_JSON} but holds {stored.stored_count()} stored episodes (its "
            f"{RUN_JSON} was lost?); pass --adopt to check its config.yaml against this config "
            "and resume it, or choose another --out"
        )
    return _adopt(cfg, run_dir, stored)


def _adopt(cfg: RunConfig, run_dir: Path, stored: RunStore) -> str:
    """The run id of a run dir without run.json, once its config.yaml is this config."""
    from pipeline.planning.config import config_from_dict, safe_load_yaml

    saved = run_dir / CONFIG_YAML
    if not saved.is_file():
        raise ConfigError(
            f"--adopt: {run_dir} has no config.yaml, so its episodes cannot be checked against "
            "this config; choose another --out"
        )
    theirs = config_from_dict(safe_load_yaml(saved.read_text()) or {}, source=str(saved))
    if theirs.fingerprint() != cfg.fingerprint():
        raise ConfigError(
            f"--adopt: {saved} is a different config (fingerprint {theirs.fingerprint()} vs "
            f"{cfg.fingerprint()}); results of two configs are never mixed"
        )
    ids = set(stored.episodes(columns=["run_id"]).column("run_id").to_pylist())
    if len(ids) > 1:
        raise ConfigError(f"--adopt: {run_dir} holds episodes of several runs: {sorted(ids)}")
    run_id = ids.pop() if ids else uuid.uuid4().hex[:12]
    log.warning("adopting %s (run %s): its %s was missing", run_dir, run_id, RUN_JSON)
    return str(run_id)


def check_run_dir_intact(run_dir: Path, markers: tuple[str, ...] = MARKERS) -> None:
    """Raise RunDirLostError when the run dir lost ``markers`` (deleted mid-run)."""
    missing = [n for n in markers if not (run_dir / n).exists()]
    if missing:
        raise RunDirLostError(
            f"{run_dir} lost {', '.join(missing)} while this run was writing to it (deleted or "
            "unmounted?): stopping, so that nothing is written into a directory that no longer "
            "holds the run. Episodes stored there may be lost; restore the directory and run "
            "the same command again, or run again with a new --out"
        )


def check_cell_budget(cfg: RunConfig, n_tasks: int | None = None, yes: bool = False) -> None:
    """Refuse, before any work and before the plan is built, a grid of more than ``max_cells``
    cells or a plan of more than ``max_episodes`` episodes, unless confirmed."""
    n = len(cfg.cells())
    episodes = n * n_tasks * cfg.episodes_per_task if n_tasks else None
    if n > cfg.max_cells and not yes:
        shown = f" ({episodes} episodes)" if episodes else ""
        raise ConfigError(
            f"max_cells: the grid gives {n} cells{shown}, more than max_cells={cfg.max_cells}; "
            f"pass --yes to run them all, or set max_cells={n} (or higher) in the config or as "
            "an override, or shrink the grid"
        )
    if episodes is not None and episodes > cfg.max_episodes and not yes:
        raise ConfigError(
            f"max_episodes: the plan has {episodes} episodes ({n} cells x {n_tasks} tasks x "
            f"episodes_per_task={cfg.episodes_per_task}), more than max_episodes="
            f"{cfg.max_episodes}; pass --yes to run them all, or set max_episodes={episodes} "
            "(or higher), or lower episodes_per_task"
        )


def _check_tracking(cfg: RunConfig, run_dir: Path) -> None:
    """The MLflow store, before anything of the run is created (pipeline.tracking.store.check_uri)."""
    if not cfg.tracking.enabled:
        return
    from pipeline.tracking.store import check_uri, resolve_uri

    try:
        check_uri(resolve_uri(cfg.tracking.uri, run_dir))
    except RuntimeError as e:
        raise ConfigError(f"tracking.uri: {e}; fix the URI or set tracking.enabled=false") from None


def plan_run(
    cfg: RunConfig,
    run_dir: str | Path,
    yes: bool = False,
    adopt: bool = False,
    allow_code_change: bool = False,
) -> RunPlan:
    """Everything checked, nothing started; ``yes`` confirms a grid larger than max_cells."""
    run_dir = check_run_dir(run_dir, cfg.output_root)
    _check_tracking(cfg, run_dir)
    _check_names(cfg)
    # where the simulator runs (an env server: started once here, version and runtime checked)
    server, server_hello = check_env_runtime(cfg)
    tasks = _select_tasks(cfg, server)
    # the checkpoint against the env (config.json only): cameras, sizes, dims; the config the
    # run uses, saved and fingerprinted, has what this settled filled in
    cfg, fit = fit_config(cfg)
    check_cell_budget(cfg, len(tasks), yes=yes)
    _check_executor(cfg)
    run_id = _resume_or_claim(cfg, run_dir, adopt)
    version = code_version()
    checkpoint = _checkpoint(cfg, run_dir)
    meta = read_run_json(run_dir)
    if meta is not None:
        check_resume(meta, checkpoint, version, run_dir, allow_code_change)
    # cells with tau: calibrated run in a second stage, after the diagnose cell they calibrate on
    cells = [CellPlan(c.cell_id, c.idr, c.intervention) for c in cfg.cells()]
    later = {c.cell_id for c in cfg.cells() if c.calibrated_tau}
    grid = SpecGrid(
        run_id, (), tuple(tasks), cfg.episodes_per_task, cfg.seed, cfg.backbone.kind, version
    )
    specs = grid.replace(cells=tuple(c for c in cells if c.cell_id not in later))
    deferred = grid.replace(cells=tuple(c for c in cells if c.cell_id in later))
    backbone_params = dict(cfg.backbone.params)
    if isinstance(backbone_params.get("path"), str) and Path(backbone_params["path"]).exists():
        # actors may run in another working directory (or on another node with the same layout)
        backbone_params["path"] = str(Path(backbone_params["path"]).resolve())
    worker_spec = WorkerSpec(
        cfg.backbone.kind,
        backbone_params,
        cfg.env.suite,
        cfg.env.params,
        None if fit.replan_steps == "chunk" else int(fit.replan_steps),
        cfg.backbone.batched,
        server,
        envs_per_worker=cfg.executor.envs_per_worker,
        log_dir=str((run_dir / LOGS_DIR).resolve()),
        perturbations=_perturbations_of(tasks),
    )
    return RunPlan(
        cfg,
        run_dir,
        run_id,
        tasks,
        specs,
        worker_spec,
        deferred,
        version,
        checkpoint,
        fit,
        server_hello,
    )


def _checkpoint(cfg: RunConfig, run_dir: Path) -> dict[str, object] | None:
    """The checkpoint's digest, reusing run.json's when its files did not change."""
    root = checkpoint_path(cfg)
    if root is None:
        return None
    previous = (read_run_json(run_dir) or {}).get("checkpoint")
    return checkpoint_record(root, previous)


def _write_meta(plan: RunPlan) -> None:
    plan.run_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(plan.run_dir / CONFIG_YAML, dump_config(plan.cfg))
    meta: dict[str, object] = {
        "run_id": plan.run_id,
        "fingerprint": plan.cfg.fingerprint(),
        "name": plan.cfg.name,
        "code_version": plan.code_version,
    }
    if plan.checkpoint is not None:
        meta["checkpoint"] = plan.checkpoint
    if plan.env_server is not None:
        meta["env_server"] = plan.env_server
    if plan.fit is not None:
        meta["fit"] = plan.fit.record()
        if plan.fit.protocol:
            meta["protocol"] = dict(plan.fit.protocol)
    old = read_run_json(plan.run_dir)
    if old is not None:  # what earlier drivers recorded (quarantined files) is kept
        kept = old.get("quarantined")
        if kept:
            meta["quarantined"] = kept
    write_run_json(plan.run_dir, meta)


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
    run_id = _resume_or_claim(plan.cfg, plan.run_dir)
    if run_id == plan.run_id:
        return plan
    log.info("%s was claimed by run %s meanwhile: resuming it", plan.run_dir, run_id)
    return replace(
        plan,
        run_id=run_id,
        specs=plan.specs.replace(run_id=run_id),
        calibrated=plan.calibrated.replace(run_id=run_id),
    )


def _execute(plan: RunPlan) -> RunSummary:
    from pipeline.tracking.store import resolve_uri
    from pipeline.tracking.tracker import Tracker

    cfg = plan.cfg
    if cfg.executor.kind == "ray":
        # before anything is written: an unreachable cluster, or one that cannot hold the
        # actors (too few GPUs, a custom resource no node has), is one clear error
        from pipeline.execution.cluster import connect

        connect(cfg.executor)
    _write_meta(plan)
    (plan.run_dir / LOGS_DIR).mkdir(exist_ok=True)  # the actors' output (workers.worker_log)
    RUN_LOG.attach(plan.run_dir)  # the CLI's log, from now on in RUN_DIR/logs/driver.log
    store = RunStore(plan.run_dir)
    if store.quarantined:  # unreadable batches moved aside on open: said in run.json too
        was = (read_run_json(plan.run_dir) or {}).get("quarantined", [])
        update_run_json(plan.run_dir, quarantined=sorted({*was, *store.quarantined}))
    tracker = None
    if cfg.tracking.enabled:  # opened before any actor starts: a bad store is refused up front
        uri = resolve_uri(cfg.tracking.uri, plan.run_dir)
        try:
            tracker = Tracker(
                uri,
                cfg.tracking.experiment,
                plan.run_dir,
                reconnect_wait_s=cfg.tracking.reconnect_wait_s,
            )
        except RuntimeError as e:
            raise ConfigError(
                f"tracking.uri: {e}; fix the URI or set tracking.enabled=false"
            ) from None
        run_name = f"{cfg.name}-{plan.run_id}"
        tracker.start(
            run_name=run_name, run_id=plan.run_id, params=run_params(plan), cells=cfg.cells()
        )
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
            report = plan.run_dir / REPORT_MD
            try:
                if no_report:  # it would fail too: `idr-eval report RUN_DIR` rebuilds it later
                    log.error("report not written: %s", no_report)
                else:
                    report = write_report(plan.run_dir)
            except Exception as e:
                _after_stop(status, "writing the report", e)
            if tracker is not None:
                try:
                    episodes = store.episodes().to_pandas()
                    figures = sorted((plan.run_dir / FIGURES_DIR).glob("*.png"))
                    extra = [plan.run_dir / CONFIG_YAML, plan.run_dir / CALIBRATION_FILE]
                    page = report.with_suffix(".html")
                    tracker.finish(episodes, [report, page, *extra, *figures], status)
                except Exception as e:
                    _after_stop(status, f"marking the MLflow runs {status}", e)
    if all_failed:
        raise AllEpisodesFailedError(all_failed)
    return summary


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


def calibrated_specs(plan: RunPlan, store: RunStore, tracker: Tracker | None = None) -> SpecGrid:
    """The specs of the cells with ``tau: calibrated``, their tau set from the stored
    diagnose cell (the paper's rule); logged, and recorded in MLflow when tracked."""
    result = calibrate(store, plan.cfg.cells())
    for cell_id, c in result["cells"].items():
        log.info(
            "tau of %s (%s of %s in %s): %s",
            cell_id,
            c["spec"],
            c["effect"],
            c["source_cell"],
            ", ".join(f"{suite} {tau:.4g}" for suite, tau in c["tau"].items()),
        )
    if tracker is not None:
        tracker.log_calibration(result)
    suites = {t.suite for t in plan.calibrated.tasks}
    cells = []
    for cell in plan.calibrated.cells:
        taus = result["cells"][cell.cell_id]["tau"]
        missing = sorted(str(x) for x in suites - set(taus))
        if missing:
            raise RuntimeError(
                f"tau calibration: {cell.cell_id!r} has no tau for suite {missing[0]!r} (its "
                "diagnose cell stored no inferences there; see the errors in the report)"
            )
        cells.append(replace(cell, tau_by_suite={k: float(v) for k, v in taus.items()}))
    return plan.calibrated.replace(cells=tuple(cells))


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
    for grid in (plan.specs, plan.calibrated):
        for task in grid.tasks:
            n = len(grid.cells) * grid.episodes_per_task
            per_task[task.task_id] = per_task.get(task.task_id, 0) + n
    progress = Progress(len(plan.all_specs()), per_task, ex.workers * ex.envs_per_worker)
    # what the run dir holds now must still be there at each flush
    markers = tuple(n for n in MARKERS if (plan.run_dir / n).exists())
    writer = BatchWriter(
        store, ex.flush_every, check_dir=lambda: check_run_dir_intact(plan.run_dir, markers)
    )
    writer.on_flush = CompactFinishedCells(plan, store, writer.stored_keys, then=on_flush)
    sched = Scheduler(
        executor,
        writer,
        ex.max_attempts,
        total=len(plan.all_specs()),
        progress=progress,
    )
    try:
        sched.run_stage(plan.specs)
        if plan.calibrated:
            sched.run_stage(calibrated_specs(plan, store, tracker))
    finally:
        executor.close()
        progress.close()
    return sched.summary


class CompactFinishedCells:
    """After each flush, compact the cells whose every episode is now stored: a long grid
    (cells run one after another) keeps one file per finished cell and table instead of one
    per batch, for its readers and for the key scan of a resume. Then calls ``then``."""

    def __init__(
        self,
        plan: RunPlan,
        store: RunStore,
        stored_keys: Iterable[tuple[str, str, int]],
        then: Callable[[list[EpisodeResult]], None] | None = None,
    ) -> None:
        self.store, self.then = store, then
        per_cell = len(plan.tasks) * plan.cfg.episodes_per_task
        cells = [c.cell_id for c in (*plan.specs.cells, *plan.calibrated.cells)]
        stored: dict[str, int] = {}
        for cell, _, _ in stored_keys:
            stored[cell] = stored.get(cell, 0) + 1
        # cells complete at the start were compacted by the run that completed them
        self.remaining = {c: per_cell - stored.get(c, 0) for c in cells}

    def __call__(self, batch: list[EpisodeResult]) -> None:
        finished = []
        for result in batch:
            cell = result.episode.cell_id
            if cell in self.remaining:
                self.remaining[cell] -= 1
                if self.remaining[cell] == 0:
                    finished.append(cell)
        if finished:
            compact_run_dir(self.store, finished)
        if self.then is not None:
            self.then(batch)


def compact_run_dir(store: RunStore, cells: list[str] | None = None) -> dict[str, int]:
    """Merge each cell's batches (of ``cells``; None: all) into one file per table
    (pipeline.results.store: crash-safe), so that readers of a large run open one file per cell and
    table, not one per batch."""
    with critical_section():  # a signal waits: the compaction's removals are not interrupted
        merged = store.compact(cells)
    if merged:
        log.info(
            "compacted %d files of %d cells into one per cell and table",
            sum(merged.values()),
            len(merged),
        )
    return merged


def _after_stop(status: str, what: str, exc: Exception) -> None:
    """A failure while closing a run: raised after a finished run; after a stopped one only
    logged, so that it does not hide the error (or signal) that stopped the run."""
    if status == "FINISHED":
        raise exc
    log.error("%s failed after the run stopped: %s: %s", what, type(exc).__name__, exc)
