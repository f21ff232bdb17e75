"""Env suites by name; simulator modules are imported only when their suite is chosen."""

from __future__ import annotations

import difflib
import importlib
from typing import Any

from workers.envs.base import Env, TaskSpec

ENVS: dict[str, str] = {
    "fake_marker": "workers.envs.fakes:FakeMarkerEnv",
    "tabletop": "workers.envs.tabletop:TabletopEnv",
    "libero": "workers.envs.libero:LiberoEnv",
}


def _cls(suite: str) -> Any:
    if suite not in ENVS:
        close = difflib.get_close_matches(suite, list(ENVS), n=1)
        hint = f"did you mean {close[0]!r}?" if close else f"known: {sorted(ENVS)}"
        raise ValueError(f"env.suite={suite!r} is unknown; {hint}")
    module, name = ENVS[suite].split(":")
    return getattr(importlib.import_module(module), name)


def check_suite(suite: str, params: dict[str, Any] | None = None) -> None:
    from workers.backbones.factory import check_params_bind

    cls = _cls(suite)
    if params is not None:
        check_params_bind(f"env.params (suite {suite!r})", cls, params)


def suite_tasks(suite: str, params: dict[str, Any]) -> list[TaskSpec]:
    """The suite's tasks, without starting a simulator where the env class can say so."""
    cls = _cls(suite)
    if hasattr(cls, "suite_tasks"):
        return list(cls.suite_tasks(**params))
    env = cls(**params)
    try:
        return env.tasks()
    finally:
        env.close()


def make_env(suite: str, params: dict[str, Any]) -> Env:
    return _cls(suite)(**params)
