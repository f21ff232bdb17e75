"""``idr-eval``: run a config, rebuild a report, open the MLflow UI."""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from pipeline.config import ConfigError


def _cmd_run(args: argparse.Namespace) -> int:
    from pipeline.config import load_config
    from pipeline.runner import execute, plan_run

    cfg = load_config(args.config, args.overrides)
    run_dir = Path(args.out) if args.out else Path(cfg.output_root) / cfg.name
    plan = plan_run(cfg, run_dir)
    n_cells = len({s.cell_id for s in plan.specs})
    print(
        f"run {plan.run_id}: {len(plan.specs)} episodes ({n_cells} cells x {len(plan.tasks)} tasks "
        f"x {cfg.episodes_per_task}) -> {run_dir}"
    )
    summary = execute(plan)
    print(
        f"done in {summary.wall_seconds:.1f}s: {summary.stored} stored, {summary.skipped} already "
        f"stored, {summary.errors} errors, {summary.retries} retries, "
        f"{summary.actors_replaced} actors replaced"
    )
    print((run_dir / "report.md").read_text())
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from pipeline.report import write_report

    run_dir = Path(args.run_dir)
    if not (run_dir / "episodes").is_dir():
        raise ConfigError(f"{run_dir} is not a run dir (no episodes/ folder)")
    path = write_report(run_dir)
    print(path.read_text())
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="idr-eval", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true")
    sub = p.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run (or resume) the episodes of a config")
    run.add_argument("config", help="YAML config, e.g. conf/smoke.yaml")
    run.add_argument("--out", help="RUN_DIR (default: <output_root>/<name>); rerun to resume")
    run.add_argument(
        "overrides", nargs="*", help="dotted key=value overrides, e.g. executor.workers=1"
    )
    run.set_defaults(func=_cmd_run)
    rep = sub.add_parser("report", help="rebuild RUN_DIR/report.md from the Parquet files")
    rep.add_argument("run_dir")
    rep.set_defaults(func=_cmd_report)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    # Overrides may follow --out; argparse leaves those after an option as unknown args.
    args, extra = parser.parse_known_args(argv)
    if extra:
        if args.command != "run" or any("=" not in e for e in extra):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = [*args.overrides, *extra]
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    try:
        return args.func(args)
    except ConfigError as e:
        print(f"idr-eval: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
