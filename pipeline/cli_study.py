"""``idr-eval study``: the runs of a study (architecture x environment), planned and checked
together, run in order, and the paper's observations across them (STUDY/observations.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pipeline.errors import ConfigError
from pipeline.execution.signals import RunInterrupted, stop_on_signals


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


def add_study(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
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
