"""Placement on a cluster: resources per actor from config, checked against the nodes before
any work; a cluster address that does not answer is one clear error within seconds."""

from __future__ import annotations

import socket
import time
from pathlib import Path

import pytest

from pipeline import cli
from pipeline.execution.cluster import check_capacity, probe_address
from pipeline.planning.config import ConfigError, load_config
from pipeline.planning.executor_config import InActorExecutor
from workers.episode.worker import EpisodeWorker, current_node, remote_worker_class

CONF = Path(__file__).resolve().parents[3] / "conf"


def _closed_port() -> int:
    with socket.socket() as s:  # bound, then closed: nobody listens there
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _node(cpu: float, gpu: float = 0, **custom: float) -> dict[str, float]:
    return {"CPU": cpu, "GPU": gpu, "memory": 8e9, **custom}


def test_gpu_share_and_custom_resources_from_config() -> None:
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.actors_per_gpu=4",
            "executor.cpus_per_worker=2",
            "executor.resources={node_type_gpu: 0.01}",
            "executor.placement=spread",
        ],
    )
    ex = cfg.executor
    assert ex.gpu_share == 0.25
    assert ex.actor_demand() == {"CPU": 2, "GPU": 0.25, "node_type_gpu": 0.01}
    opts = remote_worker_class(ex.cpus_per_worker, ex.gpu_share, ex.resources, ex.placement)
    options = opts._default_options
    assert options["num_gpus"] == 0.25 and options["num_cpus"] == 2
    assert options["resources"] == {"node_type_gpu": 0.01}
    assert options["scheduling_strategy"] == "SPREAD"
    assert InActorExecutor(gpus_per_worker=0.5).gpu_share == 0.5


@pytest.mark.parametrize(
    ("override", "pattern"),
    [
        ("executor.actors_per_gpu=0", "actors_per_gpu"),
        ("executor.resources={GPU: 1}", "not a custom resource"),
        ("executor.resources={fast: -1}", r"resources\.fast: must be a finite number > 0"),
        ("executor.placement=pack", "placement"),
    ],
)
def test_bad_placement_settings_are_refused(override: str, pattern: str) -> None:
    with pytest.raises(ConfigError, match=pattern):
        load_config(CONF / "smoke.yaml", [override])
    with pytest.raises(ConfigError, match="disagree"):
        load_config(
            CONF / "smoke.yaml", ["executor.actors_per_gpu=2", "executor.gpus_per_worker=1"]
        )


def test_capacity_is_checked_against_the_nodes() -> None:
    cpu_nodes = [_node(4), _node(4)]
    gpu_node = [_node(8, gpu=1)]
    # GPUs asked of a CPU-only cluster: says what the cluster has
    with pytest.raises(ConfigError, match=r"GPU 1 but no node has.*2 node\(s\) with CPU 8, GPU 0"):
        check_capacity(InActorExecutor(workers=2, gpus_per_worker=1), cpu_nodes)
    # 4 actors x 0.5 GPU on one GPU: too many; 4 per GPU fit
    with pytest.raises(ConfigError, match=r"need GPU 2, but the cluster has 1 node\(s\).*GPU 1"):
        check_capacity(InActorExecutor(workers=4, gpus_per_worker=0.5), gpu_node)
    check_capacity(InActorExecutor(workers=4, actors_per_gpu=4), gpu_node)
    # an actor cannot span nodes: 3 actors of 2 CPUs do not fit on 2 nodes of 3 CPUs
    with pytest.raises(ConfigError, match="at most 2 such actor"):
        check_capacity(InActorExecutor(workers=3, cpus_per_worker=2), [_node(3), _node(3)])
    # a custom resource no node has, and one a node has
    with pytest.raises(ConfigError, match="'tpu_slice'"):
        check_capacity(InActorExecutor(workers=1, resources={"tpu_slice": 1}), cpu_nodes)
    check_capacity(
        InActorExecutor(workers=2, resources={"wide": 1}), [_node(4, wide=1), _node(4, wide=1)]
    )


def test_unreachable_cluster_is_a_clear_error_within_seconds(tmp_path, capsys) -> None:
    port = _closed_port()
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match=f"no Ray cluster answers at 127.0.0.1:{port}"):
        probe_address(f"127.0.0.1:{port}")
    with pytest.raises(ConfigError, match="expected HOST:PORT"):
        probe_address("head-node")
    with pytest.raises(ConfigError, match="dashboard"):
        probe_address("http://127.0.0.1:8265")
    # the CLI: exit 2, one line, nothing created, no Ray started
    out = tmp_path / "run"
    code = cli.main(
        ["run", str(CONF / "smoke.yaml"), "--out", str(out), f"executor.address=127.0.0.1:{port}"]
    )
    err = capsys.readouterr().err
    assert code == 2 and err.count("idr-eval: error:") == 1 and "Traceback" not in err
    assert "executor.address" in err and not out.exists()
    assert time.monotonic() - t0 < 15


def test_auto_without_a_cluster_names_the_ways_to_get_one(monkeypatch) -> None:
    port = _closed_port()
    monkeypatch.setenv("RAY_ADDRESS", f"127.0.0.1:{port}")  # what `ray job submit` would set
    with pytest.raises(ConfigError, match=r"executor.address='auto' \(127.0.0.1:\d+\)"):
        probe_address("auto")


def test_inline_episodes_record_the_hostname(tmp_path) -> None:
    from pipeline.execution.runner import plan_run

    cfg = load_config(CONF / "smoke.yaml", ["executor.kind=inline", "episodes_per_task=1"])
    plan = plan_run(cfg, tmp_path / "run")
    worker = EpisodeWorker(plan.worker_spec)
    try:
        row = worker.run_episode(plan.specs[0]).episode
    finally:
        worker.close()
    assert row.node == current_node() == socket.gethostname()


def test_ray_address_without_executor_address_is_explained(monkeypatch) -> None:
    """Inside a Ray job (RAY_ADDRESS set) a config without executor.address would start a
    local Ray against that cluster: refused, naming the fix, before Ray is touched."""
    from pipeline.execution.cluster import connect

    monkeypatch.setenv("RAY_ADDRESS", "10.0.0.1:6379")
    with pytest.raises(ConfigError, match=r"add executor\.address=auto"):
        connect(InActorExecutor())


def test_replacement_waiting_for_a_lost_node_hands_its_episode_on(tmp_path, monkeypatch) -> None:
    """Two actors lost at once, both replaced, only one replacement can start: after
    REQUEUE_AFTER_S the other's queued episode goes back to the queue (no attempt charged) for
    the started actor; with no started actor it waits, up to STARTUP_TIMEOUT_S."""
    import ray

    from pipeline.execution.executors import ray_pool
    from pipeline.execution.runner import plan_run

    cfg = load_config(CONF / "smoke.yaml", ["tracking.enabled=false"])
    plan = plan_run(cfg, tmp_path / "run")
    spec = plan.specs[0]
    cancelled: list[str] = []
    monkeypatch.setattr(ray, "wait", lambda refs, num_returns, timeout: ([], refs))
    monkeypatch.setattr(ray, "cancel", cancelled.append)
    now = time.monotonic()

    def pool(waited: float, started_actor: bool = True) -> ray_pool.RayActorPool:
        """Actor 2 (a replacement) holds the episode and has waited ``waited`` s to start;
        actor 1, when there, has started and is idle."""
        p = ray_pool.RayActorPool(plan.worker_spec, cfg.executor)
        p._busy = {1: 0, 2: 1} if started_actor else {2: 1}
        p._starting = {2: ("ping", now - waited)}
        p._calls = {"ref": ray_pool._Call(2, spec, None)}
        return p

    p = pool(5.0)  # not long yet: it keeps its episode
    assert p._watch_starting() == [] and p.in_flight() == 1
    p = pool(ray_pool.REQUEUE_AFTER_S + 1)  # actor 1 started, actor 2 still waiting
    (outcome,) = p._watch_starting()
    assert outcome.requeue and outcome.spec == spec and spec.attempt == 1
    assert p.in_flight() == 0 and p._busy[2] == 0 and cancelled == ["ref"]
    assert p.free_slots() == 1  # actor 1 takes it; the waiting replacement gets nothing
    p = pool(ray_pool.REQUEUE_AFTER_S + 1, started_actor=False)  # no started actor: it waits
    assert p._watch_starting() == [] and p.in_flight() == 1
    p = pool(ray_pool.STARTUP_TIMEOUT_S + 1, started_actor=False)
    with pytest.raises(RuntimeError, match="did not start within"):
        p._watch_starting()
