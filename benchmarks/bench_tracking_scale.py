"""MLflow at grid scale: a 100-cell grid over LIBERO's 40 tasks, logged to a local sqlite store.

Times what a run does with MLflow: ``Tracker.start`` (the parent run and one child per cell,
with their params) and ``Tracker.finish`` (per-cell metrics, the per-task tables, each child's
report slice with its figures and its progress curves, the runs ended), on synthetic episodes
(100 cells x 40 tasks x 5 episodes, 4 suites, 10 inferences each) stored in a real run dir.
Counts the metric names per child, which must not grow with tasks: the per-task numbers go to
the parent's ``tables/`` artifacts.

Writes ``benchmarks/results/tracking_scale.json``. Usage:
``python benchmarks/bench_tracking_scale.py [--cells 100] [--tasks-per-suite 10]``
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = Path(__file__).parent / "results" / "tracking_scale.json"
SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10")


def _config(cells: int):
    from pipeline.planning.config import load_config

    alphas = [round(0.01 * (i + 1), 2) for i in range(cells - 2)]
    grid = f"grid=[{{mode: [baseline, diagnose, E]}}, {{alpha: {alphas}}}]"
    return load_config(ROOT / "conf" / "smoke.yaml", [grid, "max_cells=1000"])


def _episodes(modes: dict[str, str], tasks_per_suite: int, per_task: int, run_dir: Path):
    """The synthetic episodes (a frame), also written with 10 inferences each to ``run_dir``."""
    from pipeline.results.store import EPISODE_SCHEMA, RunStore, rows_to_table
    from workers.episode.rows import EpisodeResult, EpisodeRow, StepRow

    rng = np.random.default_rng(0)
    rows = []
    for cell, mode in modes.items():
        for suite in SUITES:
            for t in range(tasks_per_suite):
                for e in range(per_task):
                    ok = bool(rng.random() < 0.6)
                    rows.append(
                        EpisodeRow(
                            run_id="bench",
                            cell_id=cell,
                            mode=mode,
                            guidance="visual",
                            strategy="zero",
                            alpha=0.08,
                            beta=0.05,
                            lam=0.1,
                            tau=7.0,
                            backbone="lerobot",
                            suite=suite,
                            task_id=f"{suite}/{t}",
                            task_name=f"{suite} task {t}",
                            episode_index=e,
                            seed=0,
                            max_steps=300,
                            subtasks_total=1,
                            success=ok,
                            steps=int(rng.integers(50, 300)),
                            success_step=int(rng.integers(50, 300)) if ok else None,
                            subtasks_done=int(ok),
                            failure=None if ok else "timeout",
                            sim_seconds=10.0,
                            wall_seconds=30.0,
                            inference_ms_mean=80.0,
                            gate_rate=0.3,
                            e_img_mean=7.0,
                            e_prop_mean=2.0,
                            r_img_mean=0.7,
                        )
                    )

    def steps(row: EpisodeRow) -> list[StepRow]:
        e = rng.random((10, 2)) * 10
        return [
            StepRow(
                run_id="bench",
                cell_id=row.cell_id,
                task_id=row.task_id,
                episode_index=row.episode_index,
                inference_index=i,
                step=i * row.steps // 10,
                e_img=float(e[i, 0]),
                e_prop=float(e[i, 1]),
                r_img=float(e[i, 0] / (e[i].sum() + 1e-6)),
                gate=None if row.mode == "baseline" else float(e[i, 0] < 5),
                gripper=float(i % 2),
            )
            for i in range(10)
        ]

    RunStore(run_dir).write(EpisodeResult(r, steps(r)) for r in rows)
    return rows_to_table(rows, EPISODE_SCHEMA).to_pandas()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cells", type=int, default=100)
    ap.add_argument("--tasks-per-suite", type=int, default=10)
    ap.add_argument("--episodes-per-task", type=int, default=5)
    args = ap.parse_args()

    from mlflow import MlflowClient

    from pipeline.tracking.metrics import cell_metrics
    from pipeline.tracking.tracker import Tracker

    cfg = _config(args.cells)
    cells = cfg.cells()
    modes = {c.cell_id: c.idr.mode for c in cells}
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        run_dir.mkdir()
        episodes = _episodes(modes, args.tasks_per_suite, args.episodes_per_task, run_dir)
        uri = f"sqlite:///{Path(tmp) / 'mlflow.db'}"
        t0 = time.perf_counter()
        tracker = Tracker(uri, "bench", run_dir)
        t_open = time.perf_counter() - t0
        params = {"backbone": "lerobot", "suite": "libero", "episodes_per_task": 5}
        t0 = time.perf_counter()
        tracker.start(run_name="bench", run_id="bench", params=params, cells=cells)
        t_start = time.perf_counter() - t0
        t0 = time.perf_counter()
        cell_metrics(episodes)  # the aggregation alone (bootstrap CIs, paired tests)
        t_compute = time.perf_counter() - t0
        t0 = time.perf_counter()
        assert tracker.finish(episodes, [], "FINISHED")
        t_finish = time.perf_counter() - t0
        t0 = time.perf_counter()
        tracker._log_cell_views()  # again, alone: the children's report slices and curves
        t_views = time.perf_counter() - t0
        client = MlflowClient(uri)
        slices = sum(
            1
            for rid in tracker.children.values()
            if any(a.path == "report.html" for a in client.list_artifacts(rid))
        )
        counts = [len(client.get_run(rid).data.metrics) for rid in tracker.children.values()]
        tables = [a.path for a in client.list_artifacts(tracker.parent_id, "tables")]
    out = {
        "cells": len(cells),
        "tasks": len(SUITES) * args.tasks_per_suite,
        "episodes": len(episodes),
        "store": "sqlite (local file)",
        "open_s": round(t_open, 2),
        "start_s": round(t_start, 2),
        "finish_s": round(t_finish, 2),
        "finish_of_which_aggregation_s": round(t_compute, 2),
        "finish_of_which_cell_views_s": round(t_views, 2),
        "children_with_report_slice": slices,
        "metrics_per_child_max": max(counts),
        "metrics_per_child_min": min(counts),
        "parent_tables": tables,
        "machine": machine_record(),
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
