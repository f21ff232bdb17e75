"""``idr-eval``: run a config, rebuild a report, compare runs, open the MLflow UI."""

from __future__ import annotations

import argparse
import logging
import os
import sys
from pathlib import Path

# Arrow's buffers from the system allocator, which hands large freed blocks back to the OS at
# once; Arrow's default (mimalloc) keeps them: a report over 5 M step rows peaked at 2.3-2.6 GB
# with it, 2.0 GB without (benchmarks/bench_report_scale.py). Read by Arrow when it is first
# imported, hence here, before anything imports it; a user's own setting stands.
os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")

from pipeline.config import ConfigError
from pipeline.errors import RunError, is_disk_full
from pipeline.signals import RunInterrupted, stop_on_signals

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")


def _cmd_run(args: argparse.Namespace) -> int:
    from pipeline.config import load_config
    from pipeline.report import protocol_line
    from pipeline.runner import execute, plan_run

    cfg = load_config(args.config, args.overrides)
    run_dir = Path(args.out) if args.out else Path(cfg.output_root) / cfg.name
    plan = plan_run(
        cfg, run_dir, yes=args.yes, adopt=args.adopt, allow_code_change=args.allow_code_change
    )
    n_cells = len(plan.specs.cells) + len(plan.calibrated.cells)
    print(
        f"run {plan.run_id}: {len(plan.all_specs())} episodes ({n_cells} cells x {len(plan.tasks)} tasks "
        f"x {cfg.episodes_per_task}) -> {run_dir}"
    )
    if plan.fit is not None:
        if plan.fit.protocol:
            print(f"protocol: {protocol_line(plan.fit.protocol)}")
        for note in plan.fit.notes:
            print(f"pre-flight: {note}")
    try:
        with stop_on_signals():  # SIGTERM / SIGINT: flush, mark MLflow KILLED, exit 143 / 130
            summary = execute(plan)
    except RunInterrupted as e:
        print(
            f"idr-eval: {e}: the finished episodes are stored in {run_dir} (MLflow runs marked "
            "KILLED); run the same command again to resume",
            file=sys.stderr,
        )
        return e.exit_code
    print(
        f"done in {summary.wall_seconds:.1f}s: {summary.stored} stored, {summary.skipped} already "
        f"stored, {summary.errors} errors, {summary.retries} retries, "
        f"{summary.actors_replaced} actors replaced, {summary.timeouts} timeouts"
    )
    print((run_dir / "report.md").read_text())
    return 0


def _cmd_compact(args: argparse.Namespace) -> int:
    from pipeline.lock import RunDirLock
    from pipeline.runner import compact_run_dir
    from pipeline.store import RunStore

    run_dir = Path(args.run_dir)
    if not (run_dir / "episodes").is_dir():
        raise ConfigError(f"{run_dir} is not a run dir (no episodes/ folder)")
    with RunDirLock(run_dir):  # never alongside a driver of this run dir
        merged = compact_run_dir(RunStore(run_dir))
    print(f"{run_dir}: merged {sum(merged.values())} files of {len(merged)} cells")
    return 0


def _cmd_report(args: argparse.Namespace) -> int:
    from pipeline.report import write_report

    run_dir = Path(args.run_dir)
    if not (run_dir / "episodes").is_dir():
        raise ConfigError(f"{run_dir} is not a run dir (no episodes/ folder)")
    path = write_report(run_dir)
    print(path.read_text())
    return 0


def _cmd_compare(args: argparse.Namespace) -> int:
    from pipeline.compare import compare

    text, _ = compare(args.run_dirs, out=args.out, n_boot=args.bootstrap)
    print(text)
    if args.out:
        print(f"written to {Path(args.out) / 'compare.md'}")
    return 0


def _cmd_ui(args: argparse.Namespace) -> int:
    """Start the MLflow UI for a run's store (bound to 127.0.0.1 unless --host says otherwise)."""
    import json
    import subprocess

    from pipeline.tracking import TRACKING_FILE, default_uri

    if args.run_dir:
        state = Path(args.run_dir) / TRACKING_FILE
        if not state.is_file():
            raise ConfigError(
                f"{args.run_dir} has no {TRACKING_FILE}: was it run with tracking.enabled=false?"
            )
        uri = json.loads(state.read_text())["uri"]
    else:
        uri = default_uri(Path("runs") / "_")
    if not uri.startswith("sqlite:"):
        print(_remote_ui_help(uri))
        return 0
    cmd = [
        sys.executable,
        "-m",
        "mlflow",
        "ui",
        "--backend-store-uri",
        uri,
        "--host",
        args.host,
        "--port",
        str(args.port),
    ]
    print(f"MLflow UI for {uri} on http://{args.host}:{args.port} (Ctrl-C to stop)")
    if args.host not in LOCAL_HOSTS:
        print(
            f"idr-eval: warning: --host {args.host} makes the MLflow UI (no authentication) "
            "reachable from the network; prefer 127.0.0.1 and an SSH tunnel",
            file=sys.stderr,
        )
    return subprocess.call(cmd)


def _remote_ui_help(uri: str) -> str:
    """How to open the UI of a tracking server (it serves its own UI; nothing to start here)."""
    from urllib.parse import urlsplit

    parts = urlsplit(uri)
    host, port = parts.hostname or "SERVER", parts.port or (443 if parts.scheme == "https" else 80)
    if host in LOCAL_HOSTS:
        return f"{uri} is a tracking server on this machine: open {uri} in a browser."
    return (
        f"{uri} is a tracking server: it serves its own UI, nothing to start here. Open {uri} in "
        "a browser if it is reachable from here; otherwise (it listens on a cluster's private "
        f"network) tunnel to it and open http://127.0.0.1:{port}:\n"
        f"  ssh -N -L {port}:{host}:{port} USER@HEAD_NODE        # a VM cluster (ray up)\n"
        f"  kubectl port-forward svc/{host.split('.')[0]} {port}:{port}   # Kubernetes (KubeRay)"
    )


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
    run.set_defaults(func=_cmd_run)
    rep = sub.add_parser("report", help="rebuild RUN_DIR/report.md from the Parquet files")
    rep.add_argument("run_dir")
    rep.set_defaults(func=_cmd_report)
    cpt = sub.add_parser(
        "compact", help="merge RUN_DIR's batches into one Parquet file per cell and table"
    )
    cpt.add_argument("run_dir")
    cpt.set_defaults(func=_cmd_compact)
    cmp = sub.add_parser(
        "compare", help="one table across runs: success per suite, Avg, Δ vs baseline, p"
    )
    cmp.add_argument("run_dirs", nargs="+", metavar="RUN_DIR")
    cmp.add_argument("--out", help="folder for compare.md and the R_img heatmap across runs")
    cmp.add_argument("--bootstrap", type=int, default=2000, help="bootstrap resamples for the CI")
    cmp.set_defaults(func=_cmd_compare)
    ui = sub.add_parser("ui", help="MLflow UI for a run dir's store (default: runs/mlflow.db)")
    ui.add_argument("run_dir", nargs="?")
    ui.add_argument(
        "--host", default="127.0.0.1", help="bind address (default 127.0.0.1: local only)"
    )
    ui.add_argument("--port", type=int, default=5000)
    ui.set_defaults(func=_cmd_ui)
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
    except RunError as e:
        print(f"idr-eval: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        if not is_disk_full(e):
            raise
        print(
            f"idr-eval: error: no space left on the device ({e}); free space, then run the same "
            "command again to resume",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
