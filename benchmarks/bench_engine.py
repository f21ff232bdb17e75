"""Engine benchmarks: scheduling overhead, worker scaling, store write rate, aggregation speed.

1. Scheduling overhead per episode, inline vs Ray (1 actor), on near-instant fake episodes.
2. Throughput with 1 vs 2 Ray workers on CPU-bound fake episodes (target >= 1.8x on 2 cores).
3. Store write rate (rows/s) for synthetic episodes with 100 inference rows each.
4. Time to aggregate a synthetic steps table of 10 million rows (target <= 10 s here).

Writes ``benchmarks/results/engine.json``. Usage: ``python benchmarks/bench_engine.py``
(``--quick``: small sizes, written to a new temporary folder unless ``--out`` is given)
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig
from results_path import results_path

from pipeline.execution.cluster import init_ray
from pipeline.execution.runner import plan_run, run_episodes
from pipeline.planning.config import load_config
from pipeline.results import aggregate as agg
from pipeline.results.store import RunStore
from workers.envs.base import TaskSpec
from workers.episode.rows import EpisodeResult, EpisodeRow, EpisodeSpec, StepRow
from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "engine.json"


def _run(overrides: list[str]) -> tuple[float, int]:
    with tempfile.TemporaryDirectory() as d:
        cfg = load_config(ROOT / "conf" / "smoke.yaml", ["tracking.enabled=false", *overrides])
        plan = plan_run(cfg, Path(d) / "run")
        summary = run_episodes(plan)
        return summary.wall_seconds - summary.startup_seconds, summary.stored


def _per_episode(overrides: list[str], n: int) -> float:
    """Steady-state seconds per episode: run time after the workers are ready, over n."""
    t, stored = _run([*overrides, f"episodes_per_task={n}"])
    assert stored == n
    return t / n


def scheduling_overhead(n: int) -> dict[str, Any]:
    common = ["grid=[{mode: [baseline]}]", "env.tasks=[reach]"]
    inline = _per_episode([*common, "executor.kind=inline"], n)
    ray1 = _per_episode([*common, "executor.kind=ray", "executor.workers=1"], n)
    return {
        "episodes": n,
        "inline_ms_per_episode": inline * 1e3,
        "ray_ms_per_episode": ray1 * 1e3,
        "ray_overhead_ms_per_episode": (ray1 - inline) * 1e3,
        "method": "time after the workers are ready (actor start-up and model loading excluded) / n",
    }


def scaling(n: int, busy_s: float) -> dict[str, Any]:
    common = [
        "grid=[{mode: [E]}]",
        "env.tasks=[reach]",
        f"backbone.params.busy_s={busy_s}",
        "executor.kind=ray",
    ]
    one = _per_episode([*common, "executor.workers=1"], n)
    two = _per_episode([*common, "executor.workers=2"], n)
    return {
        "episodes": n,
        "busy_s_per_inference": busy_s,
        "one_worker_s_per_episode": one,
        "two_workers_s_per_episode": two,
        "speedup": one / two,
        "target_speedup_min": 1.8,
    }


def store_rate(episodes: int, steps_per_episode: int, batch: int) -> dict[str, Any]:
    rng = np.random.default_rng(0)
    task = TaskSpec("t", "t", max_steps=500, suite="s")
    results = []
    for i in range(episodes):
        spec = EpisodeSpec(
            "r", f"c{i % 4}", RefinerConfig(), InterventionConfig(), task, i, 0, "fake_marker"
        )
        ep = EpisodeRow.from_spec(spec, success=True)
        steps = [
            StepRow(
                run_id="r",
                cell_id=spec.cell_id,
                task_id="t",
                episode_index=i,
                inference_index=k,
                step=5 * k,
                e_img=float(rng.random()),
                e_prop=1.0,
                r_img=0.5,
                gate=1.0,
                w_prop=0.05,
                action_base=[0.1] * 7,
                action_final=[0.2] * 7,
                gripper=1.0,
                inference_ms=3.0,
            )
            for k in range(steps_per_episode)
        ]
        results.append(EpisodeResult(ep, steps))
    with tempfile.TemporaryDirectory() as d:
        store = RunStore(d)
        t0 = time.perf_counter()
        for i in range(0, episodes, batch):
            store.write(results[i : i + batch])
        dt = time.perf_counter() - t0
    rows = episodes * (steps_per_episode + 1)
    return {
        "episodes": episodes,
        "rows": rows,
        "batch_episodes": batch,
        "seconds": dt,
        "rows_per_s": rows / dt,
    }


def aggregate_speed(n_rows: int) -> dict[str, Any]:
    rng = np.random.default_rng(0)
    n_eps = n_rows // 100
    ep = np.repeat(np.arange(n_eps), 100)
    steps = pa.table(
        {
            "cell_id": pa.array(np.array([f"c{i}" for i in range(8)])[ep % 8]),
            "task_id": pa.array(np.array([f"t{i}" for i in range(10)])[(ep // 8) % 10]),
            "episode_index": pa.array(ep // 80, pa.int64()),
            "step": pa.array(np.tile(np.arange(100) * 5, n_eps), pa.int64()),
            "e_img": pa.array(rng.random(n_rows, dtype=np.float32)),
            "e_prop": pa.array(rng.random(n_rows, dtype=np.float32)),
            "r_img": pa.array(rng.random(n_rows, dtype=np.float32)),
            "gate": pa.array((rng.random(n_rows) < 0.3).astype(np.float32)),
        }
    )
    t0 = time.perf_counter()
    per_cell, per_bin = agg.steps_summary(steps)
    dt = time.perf_counter() - t0
    assert per_cell.num_rows == 8 and per_bin.num_rows == 80
    return {"rows": n_rows, "seconds": dt, "target_seconds_max": 10.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=None, help="default: results/engine.json; --quick: a temp dir"
    )
    ap.add_argument("--quick", action="store_true", help="small sizes, for a smoke check")
    args = ap.parse_args()
    args.out = results_path(RESULTS, args.out, "--quick" if args.quick else None)
    q = args.quick
    init_ray(None, 2)
    res: dict[str, Any] = {"machine": machine_record()}
    res["scheduling_overhead"] = scheduling_overhead(10 if q else 60)
    print("scheduling overhead", res["scheduling_overhead"])
    res["scaling_1_vs_2_workers"] = scaling(4 if q else 32, 0.05)
    print("scaling", res["scaling_1_vs_2_workers"])
    res["store_write"] = store_rate(80 if q else 800, 100, 8)
    print("store", res["store_write"])
    res["aggregate_steps"] = aggregate_speed(100_000 if q else 10_000_000)
    print("aggregate", res["aggregate_steps"])
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
