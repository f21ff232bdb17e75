"""Shared fixtures: one local Ray cluster (2 CPUs) for the whole session, started lazily."""

from __future__ import annotations

import os

import pytest

os.environ.setdefault("RAY_DEDUP_LOGS", "1")
os.environ.setdefault("HF_HUB_OFFLINE", "1")  # nothing may download at run time

# MuJoCo reads its GL backend once, at its first import: choose it before any test module (or a
# library one imports) can import mujoco, so which tests share a worker never decides it
from workers.rendering import configure_rendering

configure_rendering()


@pytest.fixture(scope="session")
def ray_local():
    import ray

    if not ray.is_initialized():
        ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()
