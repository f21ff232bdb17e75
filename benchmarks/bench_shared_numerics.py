"""What reproducibility costs in the shared policy service, and what it buys.

1. Forward cost (no Ray, one torch thread, as a policy actor with policy_cpus=1 has): the policy
   service answering N requests of an IDR E cell (3 rows each), N = 1..32, on each numerical path:
   ``dynamic`` (one forward of 3N rows), ``rows=96`` (the fixed default for max_batch 32: one
   forward padded to 96 rows), ``rows=12`` (forwards of 12 rows, the last padded) and
   ``request`` (each request's own 3-row forward, in turn: in-actor's path). For the tiny VLA and
   a full-size lerobot ACT (random weights) through the lerobot adapter with its processors.
   Rounds interleave the paths; medians.
2. Closed loop (Ray, this machine's 2 cores): the default preset cut to ``--episodes`` episodes
   per task (diagnose and E, tau calibrated), run twice on each shared path (2 episode actors x
   3 envs) and once in-actor: episode rows that differ between the two runs of a path (volatile
   columns aside), the calibrated tau of each run, episodes per minute (episodes only) and the
   success rate per cell with Wilson intervals.

Writes ``benchmarks/results/shared_numerics.json``.
Usage: ``python benchmarks/bench_shared_numerics.py [--rounds 3] [--episodes 3] [--skip-loop]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = Path(__file__).parent / "results" / "shared_numerics.json"
NS = (1, 2, 4, 8, 16, 32)
PATHS: dict[str, int | str | None] = {
    "dynamic": "dynamic",
    "rows=96": 96,
    "rows=12": 12,
    "request": None,
}


def _requests(n: int, backbone: Any) -> list[Any]:
    from idr_core.interventions import InterventionConfig
    from idr_core.refiner import RefinerConfig

    from workers.backbones.base import Observation
    from workers.policy.service import InferRequest

    g = torch.Generator().manual_seed(0)
    shape = next(iter(backbone.image_shapes.values()))
    return [
        InferRequest(
            Observation(
                {c: torch.rand(1, *shape, generator=g) for c in backbone.cameras},
                torch.rand(1, backbone.state_dim, generator=g),
                ["pick up the red cube"],
            ),
            i,
            RefinerConfig(mode="E", tau=0.5),
            InterventionConfig(state_space="normalized"),
        )
        for i in range(n)
    ]


def forward_cost(rounds: int) -> dict[str, Any]:
    from training.toy_checkpoints import build_act
    from workers.backbones.factory import make_backbone
    from workers.policy.forward_shape import fix_forward_shape, set_torch_threads
    from workers.policy.service import infer_many
    from workers.policy.wrapper import IDRWrapper

    set_torch_threads(1)
    act = build_act(
        Path(tempfile.mkdtemp()) / "act", image=96, cams=("agentview", "wrist"), full_size=True
    )
    models = {
        "tiny_vla": {"path": str(ROOT / "checkpoints/tiny_vla"), "device": "cpu"},
        "lerobot_act": {"path": str(act), "device": "cpu"},
    }
    out: dict[str, Any] = {}
    for name, params in models.items():
        policies = {}
        for path, rows in PATHS.items():
            policy = IDRWrapper(make_backbone("lerobot", params))
            fix_forward_shape(policy, rows if rows != "dynamic" else None, 1)
            policies[path] = policy
        table = []
        for n in NS:
            reqs = _requests(n, policies["request"].backbone)
            times: dict[str, list[float]] = {p: [] for p in PATHS}
            for policy in policies.values():  # warm
                infer_many(policy, reqs[:1])
            for _ in range(rounds):
                for p, policy in policies.items():
                    t0 = time.perf_counter()
                    if p == "request":
                        for r in reqs:
                            infer_many(policy, [r])
                    else:
                        infer_many(policy, reqs)
                    times[p].append(time.perf_counter() - t0)
            ms = {p: statistics.median(t) * 1e3 for p, t in times.items()}
            row = {"n": n, **{f"{p}_ms": v for p, v in ms.items()}}
            row |= {f"{p}_vs_dynamic": v / ms["dynamic"] for p, v in ms.items()}
            table.append(row)
            print(
                f"{name:<11} N={n:>2}: " + ", ".join(f"{p} {v:7.1f} ms" for p, v in ms.items()),
                flush=True,
            )
        out[name] = table
    return out


SHARED = {
    "policy": "shared",
    "workers": 2,
    "cpus_per_worker": 0.5,
    "policy_cpus": 1,
    "envs_per_worker": 3,
    "batch_wait_ms": 2.0,
}
LOOP_PATHS: dict[str, tuple[dict[str, Any], int]] = {  # executor settings, runs
    "shared dynamic": ({**SHARED, "batching": "dynamic"}, 2),
    "shared rows=96": (SHARED, 2),
    "shared rows=12": ({**SHARED, "forward_rows": 12}, 2),
    "in_actor request": ({"workers": 2, "cpus_per_worker": 1}, 1),
}


def _differing(a: Path, b: Path) -> tuple[int, int, int]:
    """Episode rows of ``a`` and ``b`` that differ outside the volatile columns and the code
    version (a commit between two runs changes it, not their numbers); step rows."""
    import pandas as pd

    from pipeline.results.store import VOLATILE_COLUMNS, RunStore

    def eps(d: Path) -> pd.DataFrame:
        drop = [*VOLATILE_COLUMNS, "code_version"]
        df = RunStore(d).episodes().to_pandas().drop(columns=drop)
        return df.sort_values(["cell_id", "task_id", "episode_index"]).reset_index(drop=True)

    x, y = eps(a), eps(b)
    differ = int((~(x.eq(y) | (x.isna() & y.isna()))).any(axis=1).sum())
    return differ, RunStore(a).steps().num_rows, RunStore(b).steps().num_rows


def closed_loop(episodes: int) -> dict[str, Any]:
    import pyarrow.parquet as pq

    from pipeline.execution.runner import execute, plan_run
    from pipeline.planning.config import load_config
    from pipeline.results.aggregate import wilson

    work = Path(tempfile.mkdtemp())
    out: dict[str, Any] = {"run_dirs": str(work)}
    for path, (ex, runs) in LOOP_PATHS.items():
        dirs, rec = [], {"runs": []}
        for k in range(runs):
            overrides = [
                f"episodes_per_task={episodes}",
                "tracking.enabled=false",
                *(f"executor.{key}={value}" for key, value in ex.items()),
            ]
            cfg = load_config(ROOT / "conf" / "default.yaml", overrides)
            run_dir = work / f"{path.replace(' ', '_').replace('=', '')}_{k}"
            summary = execute(plan_run(cfg, run_dir))
            wall = summary.wall_seconds - summary.startup_seconds
            eps = pq.read_table(run_dir / "episodes").to_pandas()
            ok = eps[eps.error.isna()]
            rates = {}
            for cell, g in ok.groupby("cell_id"):
                lo, hi = wilson(int(g.success.sum()), len(g))
                rates[str(cell)] = {"success": float(g.success.mean()), "ci95": [lo, hi]}
            rec["runs"].append(
                {
                    "episodes": int(summary.stored),
                    "errors": int(summary.errors),
                    "episodes_per_min": 60 * summary.stored / wall,
                    "tau": sorted({float(t) for t in eps[eps.cell_id == "E"].tau}),
                    "numerics": sorted(set(eps.numerics.dropna())),
                    "success": rates,
                }
            )
            dirs.append(run_dir)
            print(f"{path} run {k}: {rec['runs'][-1]}", flush=True)
        if len(dirs) == 2:
            differ, s0, s1 = _differing(*dirs)
            rec |= {"episode_rows_differing": differ, "step_rows": [s0, s1]}
            print(f"{path}: {differ} episode rows differ; step rows {s0} vs {s1}", flush=True)
        out[path] = rec
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--episodes", type=int, default=3, help="closed loop: episodes per task")
    ap.add_argument("--skip-loop", action="store_true")
    ap.add_argument(
        "--recount",
        action="store_true",
        help="recount the differing rows of the closed loop's kept run dirs into the JSON",
    )
    args = ap.parse_args()
    if args.recount:
        result = json.loads(RESULTS.read_text())
        loop = result["closed_loop"]
        work = Path(loop["run_dirs"])
        for path, rec in loop.items():
            if isinstance(rec, dict) and "episode_rows_differing" in rec:
                name = path.replace(" ", "_").replace("=", "")
                differ, s0, s1 = _differing(work / f"{name}_0", work / f"{name}_1")
                rec |= {"episode_rows_differing": differ, "step_rows": [s0, s1]}
                print(f"{path}: {differ} episode rows differ; step rows {s0} vs {s1}")
        RESULTS.write_text(json.dumps(result, indent=2) + "\n")
        return
    result: dict[str, Any] = {
        "machine": machine_record(),
        "torch_threads": 1,
        "units": "ms per call answering N requests (3 rows each); *_vs_dynamic: ratio to the "
        "dynamic path in the same round",
        "forward_cost": forward_cost(args.rounds),
    }
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    if not args.skip_loop:
        import ray

        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
        result["closed_loop"] = {"episodes_per_task": args.episodes, **closed_loop(args.episodes)}
        RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
