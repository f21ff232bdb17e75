"""Cluster mode: throughput with one node vs two, and the per-episode cost of a cluster.

A real Ray cluster on this machine (tests/localcluster.py): a head and a second node started
with ``ray start``, one CPU each; this process is the driver (``executor.address``).

1. Per-episode overhead on near-instant fake episodes (busy_s=0, one actor), time after the
   workers are ready / n: inline (no Ray), local Ray (``ray.init``), the cluster with the actor
   on the driver's node, and with the actor on the other node (pinned there by a custom
   resource, ``executor.resources``).
2. Throughput on CPU-bound fake episodes (the fake backbone burns ``busy_s`` per inference):
   one node (one actor) vs two nodes (two actors, ``executor.placement=spread``).

Writes ``benchmarks/results/cluster.json``. Usage: ``python benchmarks/bench_cluster.py [--quick]``
(``--quick``: small sizes, written to a new temporary folder unless ``--out`` is given)
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from results_path import results_path

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "tests"):
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))
RESULTS = Path(__file__).parent / "results" / "cluster.json"


def _run(overrides: list[str]) -> tuple[float, int, set[str]]:
    """(seconds after the workers were ready, episodes stored, nodes they ran on)."""
    from pipeline.execution.runner import plan_run, run_episodes
    from pipeline.planning.config import load_config
    from pipeline.results.store import RunStore

    with tempfile.TemporaryDirectory() as d:
        cfg = load_config(ROOT / "conf" / "smoke.yaml", ["tracking.enabled=false", *overrides])
        plan = plan_run(cfg, Path(d) / "run")
        store = RunStore(plan.run_dir)
        summary = run_episodes(plan, store)
        nodes = set(store.episodes().column("node").to_pylist())
        return summary.wall_seconds - summary.startup_seconds, summary.stored, nodes


def _per_episode(overrides: list[str], n: int) -> tuple[float, set[str]]:
    t, stored, nodes = _run([*overrides, f"episodes_per_task={n}"])
    assert stored == n, (stored, n)
    return t / n, nodes


def _connect(address: str | None, cpus: float | None = None) -> None:
    import ray

    from pipeline.execution.cluster import init_ray

    if ray.is_initialized():
        ray.shutdown()
    init_ray(address, cpus)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--out", type=Path, default=None, help="default: results/cluster.json; --quick: a temp dir"
    )
    ap.add_argument("--quick", action="store_true", help="small sizes, for a smoke check")
    args = ap.parse_args()
    args.out = results_path(RESULTS, args.out, "--quick" if args.quick else None)
    n_fast, n_busy, busy_s = (10, 6, 0.05) if args.quick else (60, 32, 0.05)

    from localcluster import RayCluster

    one = ["grid=[{mode: [baseline]}]", "env.tasks=[reach]"]
    res: dict[str, Any] = {
        "machine": machine_record(),
        "cluster": "a head and a second node started with `ray start` on this machine, 1 CPU each",
    }
    with RayCluster() as cluster:
        t0 = time.monotonic()
        head = cluster.add_node(num_cpus=1)
        res["head_start_s"] = time.monotonic() - t0
        t0 = time.monotonic()
        other = cluster.add_node(num_cpus=1, resources={"other_node": 1})
        res["node_start_s"] = time.monotonic() - t0
        os.environ.update(cluster.client_env())  # before Ray is imported: its token, its PATH

        inline, _ = _per_episode([*one, "executor.kind=inline"], n_fast)
        _connect(None, 1)
        local, _ = _per_episode([*one, "executor.kind=ray", "executor.workers=1"], n_fast)
        _connect(cluster.address)
        on_cluster = [*one, "executor.kind=ray", f"executor.address={cluster.address}"]
        same, _ = _per_episode([*on_cluster, "executor.workers=1", "executor.resources={}"], n_fast)
        remote, nodes_remote = _per_episode(
            [*on_cluster, "executor.workers=1", "executor.resources={other_node: 1}"], n_fast
        )
        assert all(n.endswith(other.node_id) for n in nodes_remote), nodes_remote
        res["overhead"] = {
            "episodes": n_fast,
            "inline_ms_per_episode": inline * 1e3,
            "local_ray_ms_per_episode": local * 1e3,
            "cluster_same_node_ms_per_episode": same * 1e3,
            "cluster_other_node_ms_per_episode": remote * 1e3,
            "cluster_vs_local_ms_per_episode": (remote - local) * 1e3,
            "method": "near-instant fake episodes (busy_s=0), one actor; time after the workers "
            "are ready (actor start-up excluded) / n",
        }
        print("overhead", json.dumps(res["overhead"], indent=1))

        busy = [*on_cluster, "grid=[{mode: [E]}]", "env.tasks=[reach]"]
        busy += [f"backbone.params.busy_s={busy_s}", "executor.placement=spread"]
        one_node, nodes1 = _per_episode([*busy, "executor.workers=1"], n_busy)
        two_nodes, nodes2 = _per_episode([*busy, "executor.workers=2"], n_busy)
        assert len(nodes2) == 2, nodes2
        res["throughput"] = {
            "episodes": n_busy,
            "busy_s_per_inference": busy_s,
            "one_node_s_per_episode": one_node,
            "two_nodes_s_per_episode": two_nodes,
            "one_node_episodes_per_s": 1 / one_node,
            "two_nodes_episodes_per_s": 1 / two_nodes,
            "speedup": one_node / two_nodes,
            "nodes_used": {"one": len(nodes1), "two": len(nodes2)},
        }
        print("throughput", json.dumps(res["throughput"], indent=1))
        res["head_node_id"], res["other_node_id"] = head.node_id, other.node_id
        import ray

        ray.shutdown()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
