"""Where the default run's time goes: physics, rendering, inference, bookkeeping, logging.

Runs a few episodes of each task and cell of a config (default: ``conf/default.yaml``) inline in
one process, with the real env, backbone and IDR wrapper, timing:

* ``physics``: ``env.step`` (robosuite/MuJoCo substeps, controller, task progress);
* ``render_and_convert``: building the policy observation, which is where lazy images render
  (the tiny VLA reads both cameras at every inference, i.e. every ``replan_steps`` steps);
* ``inference``: ``IDRWrapper.infer`` (the backbone's processors, the batched 3B forward in
  diagnose/E cells or one forward in baseline cells, and the refiner);
* ``reset``: ``env.reset`` (the first reset of a task builds its robosuite scene);
* ``other``: the rest of the episode loop (row building, action checks);
* ``logging``: writing the episodes' rows to Parquet and logging them to a local MLflow store,
  measured after the episodes on the same rows.

With ``--run-dir`` it also reads a finished run of that config and reports its episodes per
minute (wall clock from the first episode's start to the last one's end). Writes
``benchmarks/results/default_run.json``.

Usage: ``python benchmarks/bench_default_run.py [--config conf/default.yaml] [--episodes 2]
[--run-dir runs/default] [key=value ...]``
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from collections import defaultdict
from dataclasses import replace
from datetime import datetime
from pathlib import Path
from typing import Any

RESULTS = Path(__file__).parent / "results" / "default_run.json"


class Timers:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def wrap(self, name: str, fn: Any) -> Any:
        def timed(*args: Any, **kwargs: Any) -> Any:
            t0 = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                self.seconds[name] += time.perf_counter() - t0
                self.calls[name] += 1

        return timed


def run_dir_throughput(run_dir: Path) -> dict[str, Any]:
    import dataclasses

    from pipeline.results import aggregate as agg
    from pipeline.results.store import RunStore

    eps = RunStore(run_dir, read_only=True).episodes().to_pandas()
    start = min(datetime.fromisoformat(s) for s in eps["started_at"])
    end = max(datetime.fromisoformat(s) for s in eps["finished_at"])
    minutes = (end - start).total_seconds() / 60
    return {
        "run_dir": str(run_dir),
        "episodes": len(eps),
        "workers": int(eps["worker"].nunique()),
        "wall_minutes": minutes,
        "episodes_per_minute": len(eps) / minutes,
        "episode_seconds_mean": float(eps["wall_seconds"].mean()),
        "env_steps_mean": float(eps["steps"].mean()),
        "success_by_cell_task": {
            f"{c}/{t}": float(g["success"].mean())
            for (c, t), g in eps.groupby(["cell_id", "task_id"])
        },
        # each cell against the reference on the same episodes: the report's main table
        "reference": agg.reference_cell(set(eps["cell_id"])),
        "paired": [dataclasses.asdict(d) for d in agg.paired_vs_baseline(eps)],
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", type=Path, default=Path("conf/default.yaml"))
    ap.add_argument("--episodes", type=int, default=2, help="per task per cell")
    ap.add_argument("--run-dir", type=Path, default=None)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("overrides", nargs="*", help="dotted key=value config overrides")
    args = ap.parse_args()

    import torch

    torch.set_num_threads(1)  # as in a Ray actor with one CPU
    import workers.episode.observation as observation
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import load_config
    from pipeline.results.store import RunStore
    from pipeline.tracking.tracker import Tracker
    from workers.episode.worker import EpisodeWorker
    from workers.hardware import machine_record

    cfg = load_config(args.config, [*args.overrides, f"episodes_per_task={args.episodes}"])
    tmp = Path(tempfile.mkdtemp(prefix="bench_default_"))
    plan = plan_run(cfg, tmp / "run")
    worker = EpisodeWorker(plan.worker_spec)
    timers = Timers()
    worker.env.step = timers.wrap("physics", worker.env.step)
    worker.env.reset = timers.wrap("reset", worker.env.reset)
    observation.to_policy_observation = timers.wrap(
        "render_and_convert", observation.to_policy_observation
    )
    worker.policy.infer = timers.wrap("inference", worker.policy.infer)

    results, per_cell, episode_seconds, env_steps = [], {}, 0.0, 0
    tau = None
    for spec in plan.all_specs():
        if spec in plan.calibrated:  # tau: the diagnose cell's mean E_img, as the runner does
            if tau is None:
                e = [s.e_img for r in results for s in r.steps if s.e_img is not None]
                tau = sum(e) / len(e)
            spec = replace(spec, idr=replace(spec.idr, tau=tau))
        before = dict(timers.seconds)
        t0 = time.perf_counter()
        res = worker.run_episode(spec)
        dt = time.perf_counter() - t0
        if res.episode.error:
            raise RuntimeError(res.episode.error)
        results.append(res)
        episode_seconds += dt
        env_steps += res.episode.steps
        cell = per_cell.setdefault(spec.cell_id, defaultdict(float))
        cell["episodes"] += 1
        cell["seconds"] += dt
        cell["env_steps"] += res.episode.steps
        for k, v in timers.seconds.items():
            cell[k] += v - before.get(k, 0.0)
    worker.close()

    t0 = time.perf_counter()
    RunStore(tmp / "run").write(results)
    store_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tracker = Tracker(f"sqlite:///{tmp}/mlflow.db", "bench", tmp / "run")
    mlflow_open_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tracker.start(run_name="bench", run_id=plan.run_id, params={}, cells=cfg.cells())
    tracker.finish(RunStore(tmp / "run").episodes().to_pandas(), [], "FINISHED")
    mlflow_s = time.perf_counter() - t0

    parts = {k: timers.seconds[k] for k in ("reset", "physics", "render_and_convert", "inference")}
    parts["other"] = episode_seconds - sum(parts.values())
    out: dict[str, Any] = {
        "config": str(args.config),
        "episodes": len(results),
        "env_steps": env_steps,
        "inferences": timers.calls["inference"],
        "episode_seconds": episode_seconds,
        "ms_per_env_step": episode_seconds / env_steps * 1e3,
        "share": {k: v / episode_seconds for k, v in parts.items()},
        "seconds": parts,
        "ms_per_call": {
            k: timers.seconds[k] / timers.calls[k] * 1e3 for k in timers.calls if timers.calls[k]
        },
        "per_cell": {c: dict(v) for c, v in per_cell.items()},
        "logging_seconds": {
            "parquet": store_s,
            "mlflow_log": mlflow_s,
            "mlflow_open_store": mlflow_open_s,  # once per run (sqlite schema on first use)
        },
        "logging_share_of_episode_time": (store_s + mlflow_s) / episode_seconds,
        "note": "inline, one process, torch 1 thread; shares are of the summed episode time",
        "machine": machine_record(),
    }
    if args.run_dir is not None and (args.run_dir / "episodes").is_dir():
        out["run"] = run_dir_throughput(args.run_dir)
    elif args.run_dir is not None:
        out["run"] = {"run_dir": str(args.run_dir), "missing": "no episodes: run `make run` first"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
