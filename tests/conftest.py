"""Shared fixtures: one local Ray cluster (2 CPUs) for the whole session, started lazily."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("RAY_DEDUP_LOGS", "1")
os.environ.setdefault("HF_HUB_OFFLINE", "1")  # nothing may download at run time
# One OpenMP thread per process, as Ray gives its actors: the two xdist workers already keep
# both cores busy, and a torch process with two OpenMP threads then waits at every parallel op
# for a core the other worker holds (measured on the 2-core AMD EPYC, the other core busy: a toy
# pi0 forward 3.8 s with two threads, 0.035 s with one). Set before torch loads (libgomp reads it
# then); the processes the tests start (lerobot-train, lerobot-eval, the CLI) inherit it.
os.environ.setdefault("OMP_NUM_THREADS", "1")

# MuJoCo reads its GL backend once, at its first import: choose it before any test module (or a
# library one imports) can import mujoco, so which tests share a worker never decides it
from workers.rendering import configure_rendering

configure_rendering()

#: The longest test files, longest first (``make test``'s --durations on a 2-core AMD EPYC). With
#: ``--dist loadfile --no-loadscope-reorder`` xdist hands files out in collection order as a
#: worker frees up, so these start first and the short files fill in around them: a long file
#: left for last would run alone on one core while the other idles.
LONG_FIRST: tuple[str, ...] = (
    "tests/pipeline/execution/test_slurm.py",
    "tests/training/test_zoo.py",
    "tests/pipeline/execution/test_shared_policy_real.py",
    "tests/pipeline/results/test_portable_digest.py",
    "tests/workers/envs/test_lerobot_env_parity.py",
    "tests/lerobot_policy_idr/test_lerobot_tools.py",
    "tests/workers/envs/test_libero_parity.py",
    "tests/training/test_zoo_evaluator.py",
    "tests/pipeline/execution/test_cluster.py",
    "tests/pipeline/reporting/test_observations_seeds.py",
    "tests/workers/envs/test_libero_pro_sim.py",
    "tests/benchmarks/test_bench_gpu_supply.py",
    "tests/pipeline/tracking/test_tracking_server.py",
    "tests/workers/envs/test_libero.py",
)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The long files first, each file's tests kept in their order (a stable sort)."""
    rank = {path: i for i, path in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::", 1)[0], len(rank)))


@pytest.fixture(scope="session")
def ray_local():
    import ray

    if not ray.is_initialized():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()
