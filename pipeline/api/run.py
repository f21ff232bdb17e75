"""``evaluate``: one run as ``idr-eval run`` makes it, from Python, and what it measured.

The CLI's ``run`` is a thin caller of :func:`evaluate`: the same config loading (a YAML path, a
mapping or a :class:`RunConfig`, with dotted overrides), the same pre-flight (every check before
any work, bad input as :class:`ConfigError` with the message the CLI prints), the same run dir,
resume, report and MLflow runs. What it returns reads the run dir's own files, so a result is
the same whether the episodes ran now, ran in an earlier call (resume) or came from the CLI.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from pipeline.api.offline import hf_offline
from pipeline.errors import ConfigError
from pipeline.execution.signals import RunInterrupted

if TYPE_CHECKING:
    import pandas as pd
    import pyarrow as pa

    from pipeline.execution.scheduler import RunSummary
    from pipeline.planning.config import RunConfig
    from pipeline.planning.plan import RunPlan
    from pipeline.results.aggregate import PairedDiff

log = logging.getLogger("idr_eval.api")

#: what :func:`evaluate` takes as a config: a YAML path, a mapping of its keys, a RunConfig
type ConfigSource = str | Path | Mapping[str, Any] | RunConfig
#: dotted overrides: ``["key.sub=value", ...]`` or ``{"key.sub": value}``
type Overrides = Sequence[str] | Mapping[str, Any]


class EvaluationInterrupted(RunInterrupted):
    """A SIGTERM / SIGINT stopped :func:`evaluate` (a ``KeyboardInterrupt``): the finished
    episodes are stored in ``run_dir``; the same call again resumes."""

    def __init__(self, signum: int, run_dir: Path) -> None:
        super().__init__(signum)
        self.run_dir = run_dir


@dataclass(frozen=True)
class ReportData:
    """The numbers behind a run's report, as tables (``pipeline.results.aggregate``; rates in
    [0, 1], Wilson 95% intervals, error episodes excluded and counted apart)."""

    success: pd.DataFrame  # per cell: n, successes, errors, success_rate, ci_low, ci_high
    success_by_task: pd.DataFrame  # the same per cell x suite x task
    paired: list[PairedDiff]  # each cell vs the reference cell on identical episode keys
    diagnostics: pd.DataFrame  # per cell: gate_rate, e_img_mean, e_prop_mean, r_img_mean
    chains: pd.DataFrame  # chain tasks: i/N rates and Avg Len with a bootstrap interval
    # per cell: metric (r_img, gate_rate) -> [(progress percent, mean)]: the progress figures
    progress: dict[str, dict[str, list[tuple[int, float]]]]


class RunResult:
    """One run dir's tables, calibration and report data, read on first use (a run's step
    table may hold millions of rows: nothing is read that is not asked for)."""

    def __init__(self, run_dir: str | Path, summary: RunSummary | None = None) -> None:
        self.run_dir = Path(run_dir)
        self.summary = summary  # what this call did (None: opened with :func:`open_run`)

    def __repr__(self) -> str:
        return f"RunResult({str(self.run_dir)!r})"

    @cached_property
    def run_id(self) -> str:
        from pipeline.rundir import read_run_json

        return str((read_run_json(self.run_dir) or {}).get("run_id", ""))

    @cached_property
    def config(self) -> RunConfig:
        """The resolved config the run ran (RUN_DIR/config.yaml)."""
        from pipeline.planning.config import load_run_record
        from pipeline.rundir import CONFIG_YAML

        return load_run_record(self.run_dir / CONFIG_YAML)

    @cached_property
    def episodes(self) -> pa.Table:
        """One row per episode, keyed by (cell_id, task_id, episode_index)."""
        from pipeline.results.store import RunStore

        return RunStore(self.run_dir, read_only=True).episodes()

    @cached_property
    def steps(self) -> pa.Table:
        """One row per inference: the step, E_img, E_prop, R_img, gate, the actions."""
        from pipeline.results.store import RunStore

        return RunStore(self.run_dir, read_only=True).steps()

    @cached_property
    def calibration(self) -> dict[str, Any] | None:
        """RUN_DIR/calibration.json (the calibrated cells' tau); None when nothing was."""
        from pipeline.results.calibration import read_calibration

        return read_calibration(self.run_dir)

    @cached_property
    def report(self) -> ReportData:
        """The report's tables and the data of its progress figures."""
        from pipeline.reporting.figures import progress_curves
        from pipeline.reporting.run_data import load_run
        from pipeline.results import aggregate as agg

        data = load_run(self.run_dir)
        eps = data.episodes
        return ReportData(
            success=agg.success_overall(eps),
            success_by_task=agg.success_by_task(eps),
            paired=agg.paired_vs_baseline(eps),
            diagnostics=agg.diagnostics_by_cell(eps),
            chains=agg.chain_metrics(eps),
            progress=progress_curves(data) if not data.steps.empty else {},
        )

    @property
    def report_path(self) -> Path:
        from pipeline.rundir import REPORT_MD

        return self.run_dir / REPORT_MD


def open_run(run_dir: str | Path) -> RunResult:
    """The result of a run dir made earlier (by :func:`evaluate` or ``idr-eval run``)."""
    from pipeline.rundir import EPISODES_DIR

    run_dir = Path(run_dir)
    if not (run_dir / EPISODES_DIR).is_dir():
        raise ConfigError(f"{run_dir} is not a run dir (no episodes/ folder)")
    return RunResult(run_dir)


def override_strings(overrides: Overrides) -> list[str]:
    """Dotted overrides as the CLI takes them: ``["key.sub=value", ...]`` as given, or a
    mapping ``{"key.sub": value}`` written as YAML values (parsed back by the same rule)."""
    if isinstance(overrides, Mapping):
        out = []
        for key, value in overrides.items():
            text = yaml.safe_dump(value, default_flow_style=True, width=1 << 30)
            text = text.removesuffix("...\n").strip()  # a scalar's document end marker
            out.append(f"{key}={text}")
        return out
    if isinstance(overrides, str):
        raise ConfigError(f"overrides={overrides!r}: give a list of key=value strings or a dict")
    return [str(o) for o in overrides]


def load(
    config: ConfigSource, overrides: Overrides = (), out: str | Path | None = None
) -> RunConfig:
    """The validated config (ConfigError otherwise): a YAML path, a mapping of its keys or a
    RunConfig, with dotted overrides applied. ``out``: an existing run dir whose saved config
    explains the error gets a note (as the CLI's)."""
    from pipeline.execution.claim import misplaced_keys_note
    from pipeline.planning.config import RunConfig, config_from_dict, load_config
    from pipeline.planning.config_yaml import apply_overrides

    texts = override_strings(overrides)
    try:
        if isinstance(config, str | Path):
            return load_config(config, texts)
        if isinstance(config, RunConfig):
            return config_from_dict(apply_overrides(_given_keys(config), texts))
        if isinstance(config, Mapping):
            return config_from_dict(apply_overrides(dict(config), texts))
        raise ConfigError(
            f"config: a YAML path, a mapping or a RunConfig, not {type(config).__name__}"
        )
    except ConfigError as e:
        note = misplaced_keys_note(Path(out)) if out else None
        if note is None:
            raise
        raise ConfigError(f"{e}\n  {note}") from None


def _given_keys(config: RunConfig) -> dict[str, Any]:
    """``config`` as the keys it was given (a default is validated again to itself), so that an
    override switching ``executor.policy`` meets only the keys its run set, not the defaults of
    the other placement; the executor's ``policy`` always, since it picks the variant."""
    data = config.model_dump(mode="json", exclude_unset=True)
    if isinstance(data.get("executor"), dict):
        data["executor"]["policy"] = config.executor.policy
    return data


def check_in_process_rendering(cfg: RunConfig) -> None:
    """``executor.kind=inline`` runs the episodes in this process, whose worker chooses MuJoCo's
    rendering backend before MuJoCo is imported; a process that imported it already (lerobot and
    gymnasium do) without ``MUJOCO_GL`` would be refused by the worker after the run dir is
    claimed: refused here instead, before any work."""
    if cfg.executor.kind != "inline" or "mujoco" not in sys.modules or os.environ.get("MUJOCO_GL"):
        return
    raise ConfigError(
        "executor.kind=inline runs the episodes in this process, which imported MuJoCo (lerobot "
        "and gymnasium import it) before a rendering backend was chosen: set MUJOCO_GL (osmesa "
        "on a CPU, egl on a GPU) before the first import, or use executor.kind=ray (the actors "
        "are processes of their own)"
    )


def import_logging_libraries(cfg: RunConfig) -> None:
    """Import Ray and MLflow now, where the run uses them, and send their log records to the
    run's log (pipeline.execution.run_log): each installs its own terminal handler when imported."""
    from pipeline.execution.run_log import RUN_LOG

    if cfg.executor.kind == "ray":
        import ray  # noqa: F401
    if cfg.tracking.enabled:
        import mlflow  # noqa: F401
    RUN_LOG.route_libraries()


def describe_plan(plan: RunPlan) -> list[str]:
    """What the run will do, in the lines ``idr-eval run`` prints before it starts."""
    from pipeline.reporting.markdown import protocol_line

    cfg, run_dir = plan.cfg, plan.run_dir
    cells = [c.cell_id for c in (*plan.specs.cells, *plan.calibrated.cells)]
    lines = [
        f"run {plan.run_id}: {len(plan.all_specs())} episodes = {len(cells)} cells "
        f"({', '.join(cells[:8])}{', ...' if len(cells) > 8 else ''}) x {len(plan.tasks)} tasks "
        f"({', '.join(t.task_id for t in plan.tasks[:6])}{', ...' if len(plan.tasks) > 6 else ''})"
        f" x {cfg.episodes_per_task} episodes -> {run_dir} (logs in {run_dir / 'logs'})"
    ]
    if plan.fit is not None:
        if plan.fit.protocol:
            lines.append(f"protocol: {protocol_line(plan.fit.protocol)}")
        lines += [f"pre-flight: {note}" for note in plan.fit.notes]
    if plan.numerics == "remote":
        lines.append("numerics: remote (the policy server's forward shapes are its own)")
    elif plan.numerics.startswith("dynamic"):
        lines.append(
            "numerics: dynamic batching: reruns differ in float rounding "
            "(executor.batching=fixed gives the same tables every run)"
        )
    return lines


def evaluate(
    config: ConfigSource,
    out: str | Path | None = None,
    overrides: Overrides = (),
    *,
    yes: bool = False,
    adopt: bool = False,
    allow_code_change: bool = False,
    allow_numerics_change: bool = False,
    echo: Callable[[str], None] | None = None,
) -> RunResult:
    """Run (or resume) ``config`` into ``out`` exactly as ``idr-eval run CONFIG --out OUT
    OVERRIDES`` does, and return the run's result.

    ``config``: a YAML path, a mapping of its keys, or a RunConfig; ``overrides``: dotted
    ``key=value`` strings or a ``{"key.sub": value}`` mapping; ``out``: the run dir (default
    ``<output_root>/<name>``; an existing one of the same config is resumed). ``yes``,
    ``adopt``, ``allow_code_change``, ``allow_numerics_change``: the CLI's flags. ``echo``: where
    the lines the CLI prints go (default: the ``idr_eval.api`` logger at INFO).

    Raises :class:`ConfigError` for bad input before any work (nothing written), a
    :class:`~pipeline.errors.RunError` for a fault while running, and
    :class:`EvaluationInterrupted` (a KeyboardInterrupt) on SIGTERM / SIGINT in the main thread,
    after the finished episodes are stored. Hugging Face hubs are offline for the call
    (:func:`pipeline.api.offline.hf_offline`) unless the environment says otherwise.
    """
    from pipeline.execution.runner import execute, plan_run
    from pipeline.execution.signals import stop_on_signals

    say = echo or log.info
    with hf_offline():
        cfg = load(config, overrides, out)
        run_dir = Path(out) if out is not None else Path(cfg.output_root) / cfg.name
        import_logging_libraries(cfg)
        plan = plan_run(
            cfg,
            run_dir,
            yes=yes,
            adopt=adopt,
            allow_code_change=allow_code_change,
            allow_numerics_change=allow_numerics_change,
        )
        # after the pre-flight, whose refusals name the config's own faults first
        check_in_process_rendering(cfg)
        for line in describe_plan(plan):
            say(line)
        try:
            with stop_on_signals():  # SIGTERM / SIGINT: flush, mark MLflow KILLED, then raise
                summary = execute(plan)
        except RunInterrupted as e:
            raise EvaluationInterrupted(e.signum, plan.run_dir) from None
    say(
        f"done in {summary.wall_seconds:.1f}s: {summary.stored} stored, {summary.skipped} already "
        f"stored, {summary.errors} errors, {summary.retries} retries, "
        f"{summary.actors_replaced} actors replaced, {summary.timeouts} timeouts"
    )
    return RunResult(plan.run_dir, summary)
