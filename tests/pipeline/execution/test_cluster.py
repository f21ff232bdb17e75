"""A real multi-node Ray cluster on this machine: a head and a second node started with
``ray start`` (own ports, temp dirs and process sessions), the smoke preset submitted as a Ray
Job with the README's command, episodes on both nodes, then the second node killed mid-run:
the run still finishes with every key stored exactly once. Each node declares one GPU (Ray
takes the count as given; the fake backbone uses none) and the actors ask for half of one
(executor.actors_per_gpu=2), so fractional placement runs for real. Meanwhile a run asking for
more GPUs than a node has is refused, naming what the cluster has.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from localcluster import BIN, FAST_HEALTH_CHECK, RayCluster

ROOT = Path(__file__).resolve().parents[3]
pytestmark = [pytest.mark.slow, pytest.mark.timeout(420)]


@pytest.fixture(scope="module")
def cluster():
    with RayCluster(env=FAST_HEALTH_CHECK) as c:
        c.add_node(num_cpus=1, num_gpus=1, dashboard=True)  # the Jobs API, the driver, 1 actor
        c.add_node(num_cpus=1, num_gpus=1)  # the node that will be lost
        yield c


def _stored(run_dir: Path) -> list[dict]:
    rows = []
    for f in sorted((run_dir / "episodes").glob("cell=*/*.parquet")):  # batches, compacted
        cols = ["cell_id", "task_id", "episode_index", "node", "error", "attempt"]
        rows += pq.read_table(f, columns=cols).to_pylist()
    return rows


def test_job_on_two_nodes_survives_losing_one(cluster, tmp_path) -> None:
    head, lost = cluster.nodes
    run_dir = tmp_path / "run"
    episodes_per_task = 4
    total = 2 * 2 * episodes_per_task  # smoke: 2 cells x 2 tasks
    # the README's command; the job's driver joins this cluster through RAY_ADDRESS (auto)
    cmd = [
        str(BIN / "ray"),
        "job",
        "submit",
        "--address",
        cluster.dashboard_url,
        "--working-dir",
        ".",
        "--",
        "idr-eval",
        "run",
        "conf/smoke.yaml",
        "--out",
        str(run_dir),
        "executor.address=auto",
        "executor.placement=spread",
        "executor.actors_per_gpu=2",
        "executor.flush_every=1",
        f"episodes_per_task={episodes_per_task}",
        "backbone.params.busy_s=0.2",  # CPU-bound fake inference: episodes of ~0.3-2 s
        "tracking.enabled=false",
    ]
    log = tmp_path / "job.log"
    t0 = time.monotonic()
    with open(log, "w") as out:
        job = subprocess.Popen(
            cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, env=cluster.client_env()
        )
        # meanwhile (it overlaps the job's start-up): a run asking for more GPUs than a node has
        greedy = subprocess.Popen(
            [
                str(BIN / "idr-eval"),
                "run",
                "conf/smoke.yaml",
                "--out",
                str(tmp_path / "greedy"),
                f"executor.address={cluster.address}",
                "executor.gpus_per_worker=2",
            ],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env=cluster.client_env(),
        )
        try:
            # as soon as the second node has stored an episode, lose it
            deadline = time.monotonic() + 240
            while True:
                rows = _stored(run_dir) if run_dir.is_dir() else []
                if any(r["node"].endswith(lost.node_id) for r in rows):
                    break
                assert job.poll() is None, f"job ended early:\n{log.read_text()[-4000:]}"
                assert time.monotonic() < deadline, f"not on both nodes:\n{log.read_text()[-4000:]}"
                time.sleep(0.1)
            stored_before = len(rows)
            assert stored_before < total, "the run was done before the node was lost"
            lost.kill()
            t_kill = time.monotonic()
            rc = job.wait(timeout=300)
            greedy_out, greedy_err = greedy.communicate(timeout=120)
        finally:
            for p in (job, greedy):
                if p.poll() is None:
                    p.kill()
    # refused in seconds, saying what the cluster has; nothing created, no actor started
    assert greedy.returncode == 2, greedy_out + greedy_err
    assert "asks for GPU 2 but no node has that much" in greedy_err, greedy_err
    assert "the cluster has 2 node(s) with CPU 2, GPU 2" in greedy_err, greedy_err
    assert not (tmp_path / "greedy").exists()
    text = log.read_text()
    assert rc == 0 and "succeeded" in text, text[-4000:]
    rows = _stored(run_dir)
    keys = [(r["cell_id"], r["task_id"], r["episode_index"]) for r in rows]
    assert len(keys) == total and len(set(keys)) == total  # every key exactly once
    assert not [r for r in rows if r["error"]], "an episode was stored as an error"
    nodes = {r["node"].rsplit("/", 1)[-1] for r in rows}
    assert nodes == {head.node_id, lost.node_id}
    after = [r for r in rows if r["node"].endswith(lost.node_id)]
    assert len(after) < total  # the lost node stopped taking episodes
    assert "actors replaced" in text and " 0 actors replaced" not in text, text[-3000:]
    assert "2 actor(s) of {CPU 1, GPU 0.5}" in text  # the placement the cluster was checked for
    print(
        f"\n{total} episodes: {stored_before} stored before the node was lost, "
        f"{len(after)} ran on it; job {t_kill - t0:.1f} s until the loss, "
        f"{time.monotonic() - t_kill:.1f} s after"
    )
