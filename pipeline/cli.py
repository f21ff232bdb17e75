"""``idr-eval``: run a config, rebuild a report, compare runs, open the MLflow UI."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

# Arrow's buffers from the system allocator, which hands large freed blocks back to the OS at
# once; Arrow's default (mimalloc) keeps them: a report over 5 M step rows peaked at 2.3-2.6 GB
# with it, 2.0 GB without (benchmarks/bench_report_scale.py). Read by Arrow when it is first
# imported, hence here, before anything imports it; a user's own setting stands.
os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")
# Nothing downloads from a model or dataset hub at run time: a checkpoint that names a
# sub-model by hub id (SmolVLA's VLM, X-VLA's tokenizer) resolves it from the local cache
# (make setup installs the zoo's) instead of asking the hub first, which offline cost minutes
# of retries per load. Read by huggingface_hub when first imported, hence here; a local Ray's
# actors inherit it; a user's own setting stands (HF_HUB_OFFLINE=0 allows downloads).
# pipeline.api.evaluate sets the same flags (pipeline.api.offline.OFFLINE_ENV) for its call,
# also in a process that imported huggingface_hub first.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

from pipeline.cli_reliance import add_reliance
from pipeline.errors import RunError, is_disk_full
from pipeline.execution.signals import RunInterrupted, stop_on_signals
from pipeline.planning.config import ConfigError
from pipeline.rundir import EPISODES_DIR


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


def _cmd_study(args: argparse.Namespace) -> int:
    """Every run of the study planned (and pre-flighted) first, then run in order; a finished
    run is skipped by its own resume. Then STUDY/observations.md from all of them."""
    from pipeline.api.run import import_logging_libraries
    from pipeline.execution.runner import execute, plan_run
    from pipeline.planning.study import check_study_plans, load_study, pin_endpoints
    from pipeline.reporting.observations import OBS_MD, RunRef, write

    only = [s for s in args.only.split(",") if s] if args.only is not None else None
    study = load_study(args.study, args.overrides, only)
    out = Path(args.out)
    plans = []
    for run in study.runs:
        import_logging_libraries(run.config)
        try:
            plan = plan_run(
                run.config,
                out / run.label,
                yes=args.yes,
                allow_code_change=args.allow_code_change,
                allow_numerics_change=args.allow_numerics_change,
            )
        except ConfigError as e:
            others = [r.label for r in study.runs if r is not run]
            hint = f"\n  or leave the run out: --only {','.join(others)}" if others else ""
            raise ConfigError(f"{run.label}: {e}{hint}") from None
        plans.append(plan)
        held = f" (+ {plan.held_out_count()} held-out to fit tau)" if plan.held_out else ""
        print(f"{run.label}: {len(plan.all_specs())} episodes{held} -> {out / run.label}")
    check_study_plans(study, plans)
    pinned = pin_endpoints(study, out)  # before the first episode of any run
    print(f"endpoints: {len(study.endpoints)} primary, pinned in {pinned}")
    for run, plan in zip(study.runs, plans, strict=True):
        try:
            with stop_on_signals():
                summary = execute(plan)
        except RunInterrupted as e:
            print(
                f"idr-eval: {e}: finished episodes are stored under {out}; run the same "
                "command again to resume the study",
                file=sys.stderr,
            )
            return e.exit_code
        print(
            f"{run.label}: done in {summary.wall_seconds:.1f}s ({summary.stored} stored, "
            f"{summary.skipped} already stored, {summary.errors} errors)"
        )
    refs = [RunRef(r.arch, r.env, out / r.label, r.seed) for r in study.runs]
    write(out, refs, study.name, study.endpoints)
    print((out / OBS_MD).read_text())
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


def _cmd_ui(args: argparse.Namespace) -> int:
    """Start the MLflow UI for the run dirs' store (127.0.0.1 unless --host says otherwise),
    printing the Compare URL of their cells (``--open``: opened in a browser)."""
    import subprocess

    from pipeline.tracking.backend import check_store, default_uri
    from pipeline.tracking.ui import LOCAL_HOSTS, remote_ui_help, select, ui_base

    sel = None
    if args.run_dirs:
        sel = select([Path(p) for p in args.run_dirs])
        uri = sel.uri
    else:
        uri = default_uri(Path("runs") / "_")
    if not uri.startswith("sqlite:"):
        print(remote_ui_help(uri))
        if sel is not None:
            print(f"the cells side by side: {sel.compare_url(ui_base(uri))}")
        return 0
    check_store(uri)
    base = ui_base(uri, args.host, args.port)
    cmd = [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", uri]
    cmd += ["--host", args.host, "--port", str(args.port), "--workers", str(args.workers)]
    print(f"MLflow UI for {uri} on {base} (Ctrl-C to stop)")
    if args.host in LOCAL_HOSTS:
        print(
            f"it listens on {args.host} only: this machine; from another one, tunnel "
            f"(ssh -N -L {args.port}:127.0.0.1:{args.port} USER@THIS_HOST) or pass --host 0.0.0.0"
        )
    else:
        print(
            f"idr-eval: warning: --host {args.host} makes the MLflow UI (no authentication) "
            "reachable from the network; prefer 127.0.0.1 and an SSH tunnel",
            file=sys.stderr,
        )
    url = sel.compare_url(base) if sel is not None and sel.runs else base
    if sel is not None and sel.runs:
        print(f"the {len(sel.runs)} cells side by side: {url}")
    # the job runner MLflow starts beside its UI serves GenAI jobs: not needed here
    env = {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false", **os.environ}
    proc = subprocess.Popen(cmd, env=env)
    if args.open:
        _open_when_up(base, url, proc)
    try:
        return proc.wait()
    except KeyboardInterrupt:
        proc.terminate()
        return proc.wait()


def _open_when_up(base: str, url: str, proc: object) -> None:
    """Open ``url`` in the user's browser once the UI answers (up to 60 s)."""
    import time
    import urllib.request
    import webbrowser

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:  # type: ignore[attr-defined]
        try:
            with urllib.request.urlopen(f"{base}/health", timeout=2):
                break
        except OSError:
            time.sleep(0.5)
    if not webbrowser.open(url):
        print(f"no browser to open here: open {url}")


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="idr-eval", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (
        _add_run,
        _add_slurm,
        _add_study,
        _add_results,
        _add_sidecar,
        _add_compare,
        _add_ui,
        _add_list,
        add_reliance,
    ):
        add(sub)
    return p


Subparsers = "argparse._SubParsersAction[argparse.ArgumentParser]"


def _add_run(sub: Subparsers) -> None:
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


def _add_slurm(sub: Subparsers) -> None:
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


def _add_study(sub: Subparsers) -> None:
    st = sub.add_parser(
        "study",
        help="run a study (architecture x environment runs, e.g. conf/paper/observations.yaml) "
        "and report the paper's observations across them",
    )
    st.add_argument("study", help="study YAML, e.g. conf/paper/observations.yaml")
    st.add_argument("--out", required=True, help="STUDY_DIR: one run dir per arch@env inside")
    st.add_argument("overrides", nargs="*", help="dotted key=value overrides for every run")
    st.add_argument("--yes", action="store_true", help="allow runs above the grid size guard")
    st.add_argument(
        "--allow-code-change",
        action="store_true",
        help="as for `run`: resume the study's run dirs made by another code version",
    )
    st.add_argument(
        "--allow-numerics-change", action="store_true", help="as for `run`, for every run"
    )
    st.add_argument(
        "--only",
        metavar="ARCH@ENV[,...]",
        help="run and report only these runs of the study (e.g. those whose checkpoints this "
        "machine holds); the report covers them alone",
    )
    st.set_defaults(func=_cmd_study)


def _add_results(sub: Subparsers) -> None:
    rep = sub.add_parser("report", help="rebuild RUN_DIR/report.md from the Parquet files")
    rep.add_argument("run_dir")
    rep.set_defaults(func=_cmd_report)
    cpt = sub.add_parser(
        "compact", help="merge RUN_DIR's batches into one Parquet file per cell and table"
    )
    cpt.add_argument("run_dir")
    cpt.set_defaults(func=_cmd_compact)


def _add_sidecar(sub: Subparsers) -> None:
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


def _add_compare(sub: Subparsers) -> None:
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


def _add_ui(sub: Subparsers) -> None:
    ui = sub.add_parser(
        "ui",
        help="MLflow UI for run dirs' store (default: runs/mlflow.db), at their cells' Compare page",
    )
    ui.add_argument("run_dirs", nargs="*", metavar="RUN_DIR")
    ui.add_argument("--open", action="store_true", help="open the Compare page in a browser")
    ui.add_argument(
        "--host", default="127.0.0.1", help="bind address (default 127.0.0.1: local only)"
    )
    ui.add_argument("--port", type=int, default=5000)
    ui.add_argument(
        "--workers", type=int, default=1, help="server processes (MLflow's default 4; one user: 1)"
    )
    ui.set_defaults(func=_cmd_ui)


def _table(rows: list[tuple[object, ...]]) -> str:
    widths = [max(len(str(r[i])) for r in rows) for i in range(len(rows[0]))]
    return "\n".join(
        "  ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)).rstrip() for r in rows
    )


def _cmd_list(args: argparse.Namespace) -> int:
    from pipeline.planning import catalog
    from pipeline.planning.config import safe_load_yaml

    what = args.what
    if what == "tasks":
        if not args.suite:
            raise ConfigError("idr-eval list tasks SUITE [key=value ...]: name a suite")
        params = {}
        for item in args.params:
            key, eq, value = item.partition("=")
            if not eq:
                raise ConfigError(f"{item!r}: env params are key=value")
            params[key] = safe_load_yaml(value)
        rows = catalog.tasks(args.suite, params)
        print(_table([("task", "name", "max steps"), *rows]))
        return 0
    sections = {
        "suites": lambda: [("suite", "what"), *catalog.suites()],
        "envs": lambda: [
            ("lerobot type", "needs", "installed", "note"),
            *[(t, m, "yes" if ok else "no", n) for t, m, ok, n in catalog.lerobot_env_types()],
        ],
        "perturbations": lambda: [("kind", "what", "suites"), *catalog.perturbation_kinds()],
        "backbones": lambda: [("backbone", "class"), *catalog.backbones()],
    }
    for name in [what] if what != "all" else list(sections):
        print(f"# {name}")
        print(_table(sections[name]()))
        print()
    return 0


def _add_list(sub: Subparsers) -> None:
    ls = sub.add_parser(
        "list",
        help="what a config can name: suites, lerobot env types (installed or not), a suite's "
        "tasks (list tasks SUITE key=value ...), perturbation kinds, backbones",
    )
    ls.add_argument(
        "what",
        nargs="?",
        default="all",
        choices=["all", "suites", "envs", "tasks", "perturbations", "backbones"],
    )
    ls.add_argument("suite", nargs="?", help="list tasks: the suite")
    ls.add_argument("params", nargs="*", help="list tasks: env params as key=value")
    ls.set_defaults(func=_cmd_list)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    # Overrides may follow --out; argparse leaves those after an option as unknown args.
    args, extra = parser.parse_known_args(argv)
    if extra:
        if args.command not in ("run", "slurm", "study") or any("=" not in e for e in extra):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = [*args.overrides, *extra]
    from pipeline.execution.run_log import RUN_LOG

    RUN_LOG.install(verbose=args.verbose)
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
