"""``idr-eval run`` and ``idr-eval slurm``: a config's episodes, on this machine's executor or
on Ray across a Slurm allocation (``pipeline.execution.slurm``)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import ConfigError


def _cmd_run(args: argparse.Namespace) -> int:
    """``pipeline.api.evaluate`` with the command's arguments; its lines printed, then the
    report and where MLflow shows the cells."""
    from pipeline.api.run import EvaluationInterrupted, evaluate

    try:
        result = evaluate(
            args.config,
            args.out,
            args.overrides,
            yes=args.yes,
            adopt=args.adopt,
            allow_code_change=args.allow_code_change,
            allow_numerics_change=args.allow_numerics_change,
            echo=print,
        )
    except EvaluationInterrupted as e:
        print(
            f"idr-eval: {e}: the finished episodes are stored in {e.run_dir} (MLflow runs marked "
            "KILLED); run the same command again to resume",
            file=sys.stderr,
        )
        return e.exit_code
    print(result.report_path.read_text())
    print(_ui_hint(result.run_dir))
    return 0


def _ui_hint(run_dir: Path) -> str:
    """Where the run's cells are side by side in the MLflow UI (or why they are not)."""
    from pipeline.tracking.ui import select, ui_base

    try:
        sel = select([run_dir])
    except ConfigError as e:
        return f"MLflow: {e}"
    start = "" if sel.uri.startswith("http") else f"`idr-eval ui {run_dir}`, then open "
    return f"MLflow: the {len(sel.runs)} cells side by side: {start}{sel.compare_url(ui_base(sel.uri))}"


def add_run(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    run = sub.add_parser("run", help="run (or resume) the episodes of a config")
    run.add_argument("config", help="YAML config, e.g. conf/smoke.yaml")
    run.add_argument("--out", help="RUN_DIR (default: <output_root>/<name>); rerun to resume")
    run.add_argument(
        "overrides", nargs="*", help="dotted key=value overrides, e.g. executor.workers=1"
    )
    run.add_argument(
        "--yes",
        action="store_true",
        help="run a grid of more than max_cells cells (16) or max_episodes episodes (100000)",
    )
    run.add_argument(
        "--adopt",
        action="store_true",
        help="resume a run dir whose run.json was lost, once its config.yaml matches the config",
    )
    run.add_argument(
        "--allow-code-change",
        action="store_true",
        help="resume a run dir made by another code version (git describe) of idr-eval",
    )
    run.add_argument(
        "--allow-numerics-change",
        action="store_true",
        help="resume a run dir on another numerical path (executor.policy / batching / "
        "forward_rows / torch_threads); the report names both",
    )
    run.set_defaults(func=_cmd_run)


def _cmd_slurm(args: argparse.Namespace) -> int:
    from pipeline.execution import slurm

    passed = ["--yes"] if args.yes else []
    passed += ["--allow-numerics-change"] if args.allow_numerics_change else []
    passed += ["--allow-code-change"] if args.allow_code_change else []
    return slurm.run(args.config, args.out, args.overrides, passed)


def add_slurm(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    sl = sub.add_parser(
        "slurm",
        help="inside a Slurm allocation: Ray on its nodes, then `run` on the first "
        "(docker/slurm.sbatch)",
    )
    sl.add_argument("config", help="YAML config, e.g. conf/smoke.yaml")
    sl.add_argument("--out", required=True, help="RUN_DIR on a filesystem every node mounts")
    sl.add_argument("overrides", nargs="*", help="dotted key=value overrides")
    sl.add_argument("--yes", action="store_true", help="as for `run`")
    sl.add_argument("--allow-code-change", action="store_true", help="as for `run`")
    sl.add_argument(
        "--allow-numerics-change",
        action="store_true",
        help="as for `run`: a requeued job that lands on other hardware resumes",
    )
    sl.set_defaults(func=_cmd_slurm)
