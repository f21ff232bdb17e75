"""Env suites by name; simulator modules are imported only when their suite is chosen."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from workers.envs.base import Env, TaskSpec, env_member
from workers.registry import check_params_bind, load_class

ENVS: dict[str, str] = {
    "fake_marker": "workers.envs.fakes:FakeMarkerEnv",
    "tabletop": "workers.envs.tabletop:TabletopEnv",
    "libero": "workers.envs.libero:LiberoEnv",
}


def env_class(suite: str) -> Any:
    """The env class of ``suite`` (its module imported; no simulator started)."""
    return load_class(ENVS, suite, "env.suite")


def check_suite(suite: str, params: dict[str, Any] | None = None) -> None:
    cls = env_class(suite)
    if params is not None:
        check_params_bind(f"env.params (suite {suite!r})", cls, params)


def suite_tasks(suite: str, params: dict[str, Any]) -> list[TaskSpec]:
    """The suite's tasks, without starting a simulator where the env class can say so; each
    with its ``suite`` set (the env's own suite name where the task names none)."""
    cls = env_class(suite)
    listing = env_member(cls, "suite_tasks")
    if listing is not None:
        tasks = list(listing(**params))
    else:
        env = cls(**params)
        try:
            tasks = env.tasks()
        finally:
            env.close()
    default = getattr(cls, "suite", None) or suite
    return [t if t.suite else replace(t, suite=default) for t in tasks]


def make_env(suite: str, params: dict[str, Any]) -> Env:
    return env_class(suite)(**params)
