"""``idr-eval report``, ``compact``, ``sidecar`` and ``compare``: what is made of stored results
(a run dir's report and its compaction, the idr plugin's diagnostics, a table across runs)."""

from __future__ import annotations

import argparse
from pathlib import Path

from pipeline.errors import ConfigError
from pipeline.rundir import EPISODES_DIR


def _cmd_compact(args: argparse.Namespace) -> int:
    from pipeline.execution.lock import RunDirLock
    from pipeline.execution.runner import compact_run_dir
    from pipeline.results.store import RunStore

    run_dir = Path(args.run_dir)
    if not (run_dir / EPISODES_DIR).is_dir():
        raise ConfigError(f"{run_dir} is not a run dir (no episodes/ folder)")
    with RunDirLock(run_dir):  # never alongside a driver of this run dir
        merged = compact_run_dir(RunStore(run_dir))
    print(f"{run_dir}: merged {sum(merged.values())} files of {len(merged)} cells")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from pipeline.reporting.write import write_report

    run_dir = Path(args.run_dir)
    if not (run_dir / EPISODES_DIR).is_dir():
        raise ConfigError(f"{run_dir} is not a run dir (no episodes/ folder)")
    path = write_report(run_dir)
    print(path.read_text())
    return 0


def add_results(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    rep = sub.add_parser("report", help="rebuild RUN_DIR/report.md from the Parquet files")
    rep.add_argument("run_dir")
    rep.set_defaults(func=_cmd_report)
    cpt = sub.add_parser(
        "compact", help="merge RUN_DIR's batches into one Parquet file per cell and table"
    )
    cpt.add_argument("run_dir")
    cpt.set_defaults(func=_cmd_compact)


def _cmd_sidecar(args: argparse.Namespace) -> int:
    from pipeline.reporting import sidecar as sidecar_report

    dirs = [Path(d) for d in args.dirs]
    for d in dirs:
        if not d.is_dir() or not any(d.glob("part-*.parquet")):
            raise ConfigError(
                f"{d} is not an IDR diagnostics folder (no part-*.parquet): give the "
                "diagnostics_dir the idr policy announced at the start of the rollout"
            )
    if args.eval_info and not Path(args.eval_info).is_file():
        raise ConfigError(
            f"--eval-info {args.eval_info} does not exist (lerobot-eval's eval_info.json)"
        )
    if args.fps is not None and not args.fps > 0:
        raise ConfigError(f"--fps {args.fps} must be > 0 (the env's control rate)")
    try:
        path = sidecar_report.write(
            dirs,
            Path(args.out),
            Path(args.eval_info) if args.eval_info else None,
            args.fps,
            args.label or None,
        )
    except ValueError as e:
        raise ConfigError(str(e)) from None
    print(path.read_text())
    print(f"written to {path}")
    return 0


def add_sidecar(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    car = sub.add_parser(
        "sidecar",
        help="report IDR's diagnostics sidecars (the idr lerobot policy on a robot or lerobot-eval)",
    )
    car.add_argument("dirs", nargs="+", metavar="DIAG_DIR", help="one cell per folder")
    car.add_argument(
        "--out", required=True, help="folder for report.md, figures/, episodes.parquet"
    )
    car.add_argument("--eval-info", help="lerobot-eval's eval_info.json: success per episode")
    car.add_argument(
        "--fps", type=float, help="control rate, for completion time under lerobot-eval"
    )
    car.add_argument("--label", action="append", help="a cell name per folder, in order")
    car.set_defaults(func=_cmd_sidecar)


def _cmd_compare(args: argparse.Namespace) -> int:
    from pipeline.reporting.compare import TablesRefused, compare
    from pipeline.tracking.ui import mlflow_lines

    try:
        text, _ = compare(
            args.run_dirs,
            out=args.out,
            n_boot=args.bootstrap,
            links=mlflow_lines,
            across_suites=args.across_suites,
        )
    except TablesRefused as e:  # no table, but the UI can still show the runs side by side
        print(e.ui_text)
        raise
    print(text)
    if args.out:
        print(f"written to {Path(args.out) / 'compare.md'}")
    return 0


def add_compare(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    cmp = sub.add_parser(
        "compare", help="one table across runs: success per suite, Avg, Δ vs baseline, p"
    )
    cmp.add_argument("run_dirs", nargs="+", metavar="RUN_DIR")
    cmp.add_argument("--out", help="folder for compare.md and the R_img heatmap across runs")
    cmp.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples for the CI")
    cmp.add_argument(
        "--across-suites",
        action="store_true",
        help="runs over different suites (one backbone, several envs): success and the diagnose "
        "cell's R_img per run x suite, unpaired (the paper's observation 1)",
    )
    cmp.set_defaults(func=_cmd_compare)
