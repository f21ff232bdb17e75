"""The checks a run passes before anything is created: names, tasks and perturbations, the
executor's resources, the grid's size and the MLflow store. Each failure is one ConfigError
naming the field and the fix."""

from __future__ import annotations

import logging
import os
from pathlib import Path

from pipeline.planning.catalog import suite_task_specs
from pipeline.planning.config import ConfigError, RunConfig
from pipeline.planning.executor_config import SharedExecutor
from workers.backbones.factory import check_backbone
from workers.envs.base import TaskSpec, suite_hooks, suite_info
from workers.envs.factory import check_suite, env_class
from workers.envs.server.spec import ServerSpec

log = logging.getLogger("idr_eval.preflight")


def check_names(cfg: RunConfig) -> None:
    try:
        check_suite(cfg.env.suite, cfg.env.params)
        check_backbone(cfg.backbone.kind, cfg.backbone.params)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def select_tasks(cfg: RunConfig, server: ServerSpec | None = None) -> list[TaskSpec]:
    """The run's tasks: env.tasks (all of the suite's by default), each crossed with
    env.perturbations unless it names its own (``pick_color@light_dim:0.4``); a perturbation
    the suite cannot apply is refused here, before any work."""
    from workers.envs.wrappers.perturbation_grammar import IMAGE_KINDS, SEP, parse, split_task
    from workers.envs.wrappers.perturbations import perturbed_task

    tasks = suite_task_specs(cfg.env.suite, cfg.env.params, server)
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
    kinds = suite_info(env_class(cfg.env.suite)).perturbation_kinds
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
    if (check := suite_hooks(env_class(cfg.env.suite)).check_tasks) is not None:
        bases = list(dict.fromkeys(split_task(t)[0] for t in out))
        try:
            check(bases, cfg.episodes_per_task, **cfg.env.params)
        except ValueError as e:
            raise ConfigError(str(e)) from None
    return list(out.values())


def perturbations_of(tasks: list[TaskSpec]) -> tuple[str, ...]:
    """The perturbations the tasks name (``none`` for plain ones); () when none is named, so
    that an unperturbed run's env is not wrapped at all."""
    from workers.envs.wrappers.perturbation_grammar import SEP, perturbation_of

    if not any(SEP in t.task_id for t in tasks):
        return ()
    return tuple(dict.fromkeys(perturbation_of(t.task_id) for t in tasks))


def check_videos(cfg: RunConfig) -> None:
    """A video camera the env does not render is refused, where the suite says what it renders
    without a simulator (a class attribute); else the first recorded episode says so."""
    camera = cfg.videos.camera
    if not cfg.videos.episodes or camera is None:
        return
    cams = getattr(env_class(cfg.env.suite), "cameras", None)
    if isinstance(cams, tuple) and cams and camera not in cams:
        raise ConfigError(f"videos.camera={camera!r}: suite {cfg.env.suite!r} renders {list(cams)}")


def check_numerics_mode(cfg: RunConfig) -> None:
    """The portable mode needs an x86-64 CPU with AVX2 (this host's, where its actors run); on a
    GPU backbone it pins the CPU's kernels only, which the log says at start."""
    ex = cfg.executor
    if ex.numerics_mode != "portable":
        return
    from workers.hardware import PORTABLE_ENV, check_portable_cpu

    local = not (ex.kind == "ray" and ex.address)
    why = check_portable_cpu() if local else None
    if why:
        raise ConfigError(
            f"executor.numerics_mode=portable pins torch, MKL and oneDNN to AVX2, but {why}: "
            "use executor.numerics_mode=native on this machine"
        )
    device = str(cfg.backbone.params.get("device") or "")
    if device.startswith("cuda"):
        log.warning(
            "executor.numerics_mode=portable pins the CPU's kernels (%s) and the CPU renderer, "
            "not the GPU's: cuBLAS / cuDNN kernels still depend on the GPU model (set "
            "CUBLAS_WORKSPACE_CONFIG and deterministic algorithms for run-to-run identity on "
            "one GPU model)",
            ", ".join(f"{k}={v}" for k, v in PORTABLE_ENV.items()),
        )


def check_executor(cfg: RunConfig) -> None:
    check_numerics_mode(cfg)
    ex = cfg.executor
    if isinstance(ex, SharedExecutor) and ex.kind != "ray":
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
                if isinstance(ex, SharedExecutor)
                else ""
            )
            raise ConfigError(
                f"executor.workers={ex.workers} x executor.cpus_per_worker={ex.cpus_per_worker}"
                f"{policy} needs {need:g} CPUs but this machine has {have}; lower "
                "executor.workers or set executor.oversubscribe=true"
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


def check_tracking(cfg: RunConfig, run_dir: Path) -> None:
    """The MLflow store, before anything of the run is created (pipeline.tracking.backend.check_uri)."""
    if not cfg.tracking.enabled:
        return
    from pipeline.tracking.backend import check_uri, resolve_uri

    try:
        check_uri(resolve_uri(cfg.tracking.uri, run_dir))
    except RuntimeError as e:
        raise ConfigError(f"tracking.uri: {e}; fix the URI or set tracking.enabled=false") from None
