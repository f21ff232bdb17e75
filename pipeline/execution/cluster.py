"""Connecting to Ray and checking, before any actor starts, that the cluster can hold the run.

``executor.address`` selects an existing cluster: ``auto`` (what ``ray job submit`` and a
KubeRay RayJob give the driver through ``RAY_ADDRESS``, or the last ``ray start`` on this
machine), ``HOST:PORT`` of a head node's GCS, or ``ray://HOST:PORT`` (Ray Client). Ray itself
retries an address that does not answer for a minute or more; :func:`probe_address` gives a
clear error within seconds instead. Without an address a local Ray is started with the CPUs
the workers ask for (and the custom resources they ask for, declared on that one node).

:func:`check_capacity` compares what the actors ask for (``ExecutorConfig.actor_demand``: CPUs,
a GPU share, custom resources) with the nodes that are up, and refuses a run the cluster cannot
hold, saying what the cluster has, instead of leaving actors pending for ever.
"""

from __future__ import annotations

import logging
import math
import os
import socket
from collections.abc import Iterable
from typing import Any

from pipeline.errors import RunError
from pipeline.execution import signals
from pipeline.planning.config import ConfigError, ExecutorConfig
from pipeline.planning.executor_config import SharedExecutor

log = logging.getLogger("idr_eval.cluster")
PROBE_TIMEOUT_S = 5.0
_EPS = 1e-9


def _host_port(address: str) -> tuple[str, int]:
    text = address.removeprefix("ray://")
    host, sep, port = text.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise ConfigError(
            f"executor.address={address!r}: expected HOST:PORT of the head node's GCS (e.g. "
            "10.0.0.1:6379), ray://HOST:10001 (Ray Client) or auto"
        )
    return host.strip("[]"), int(port)


def resolve_address(address: str) -> str:
    """``auto`` -> the address Ray would use (RAY_ADDRESS, else the last ``ray start`` here)."""
    if address != "auto":
        return address
    env = os.environ.get("RAY_ADDRESS")
    if env and env != "auto":
        return env
    from ray._private.services import canonicalize_bootstrap_address_or_die

    try:
        return canonicalize_bootstrap_address_or_die("auto")
    except (ConnectionError, ValueError) as e:
        raise ConfigError(
            "executor.address=auto: no Ray cluster to join (RAY_ADDRESS is not set and no "
            f"`ray start` ran on this machine: {str(e).splitlines()[0]}); submit with "
            "`ray job submit ... -- idr-eval run ...`, start one with `ray start --head`, or drop "
            "executor.address to run on a local Ray"
        ) from None


def probe_address(address: str, timeout_s: float = PROBE_TIMEOUT_S) -> str:
    """Refuse within ``timeout_s`` an address where no Ray head answers; returns it resolved."""
    resolved = resolve_address(address)
    if resolved.startswith(("http://", "https://")):
        raise ConfigError(
            f"executor.address={address!r} is a dashboard (Jobs API) URL: give it to `ray job "
            "submit --address`, and let the job use executor.address=auto"
        )
    host, port = _host_port(resolved)
    try:
        with socket.create_connection((host, port), timeout=timeout_s):
            pass
    except OSError as e:
        why = "timed out" if isinstance(e, TimeoutError) else (e.strerror or str(e))
        shown = f"{address!r} ({resolved})" if resolved != address else repr(address)
        raise ConfigError(
            f"executor.address={shown}: no Ray cluster answers at {host}:{port} ({why} after "
            f"{timeout_s:g} s); check the head node is up and the port is its GCS port "
            "(ray start --head --port=...), or drop executor.address to run on a local Ray"
        ) from None
    return resolved


def connect(ex: ExecutorConfig) -> None:
    """Start or join Ray for ``ex`` and check the cluster can hold its actors (ConfigError)."""
    if ex.address:
        probe_address(ex.address)
        init_ray(ex.address, None)
    elif os.environ.get("RAY_ADDRESS"):
        # ray.init would join that cluster and then refuse the local CPU count, cryptically
        raise ConfigError(
            f"RAY_ADDRESS={os.environ['RAY_ADDRESS']} is set (a Ray job sets it) but "
            "executor.address is not: add executor.address=auto to run on that cluster, or "
            "unset RAY_ADDRESS to run on a local Ray"
        )
    else:
        resources = {k: v * ex.workers for k, v in ex.resources.items()} or None
        # a local Ray takes whole CPUs only (1 x 0.5 + 1 policy CPU: 2)
        init_ray(None, math.ceil(ex.local_cpus()), resources=resources)
    if ex.autoscaling:
        log.info("executor.autoscaling: not checking the actors against the nodes up now")
        return
    check_capacity(ex, alive_nodes())


def init_ray(
    address: str | None,
    num_cpus: float | None,
    num_gpus: float | None = None,
    resources: dict[str, float] | None = None,
) -> None:
    """Connect to a cluster (``address``) or start a local one with ``num_cpus`` (and custom
    ``resources``). :func:`connect` probes the address and checks capacity first."""
    import ray

    if ray.is_initialized():
        return
    # the actors write their output to the run dir (workers.worker_log), not to this terminal
    env = {"RAY_DEDUP_LOGS": "1"}
    for k, v in env.items():
        os.environ.setdefault(k, v)
    if not address and os.environ.get("RAY_AUTH_MODE", "").lower() == "disabled":
        # Ray 2.60 turns token authentication on for a local Ray; its ports bind every address
        log.warning(
            "RAY_AUTH_MODE=disabled: this local Ray takes calls from anyone who reaches its "
            "ports (every address of this machine); unset it to keep Ray's token authentication"
        )
    try:
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            ray.init(
                num_cpus=num_cpus,
                num_gpus=num_gpus,
                resources=resources,
                include_dashboard=False,
                log_to_driver=False,
            )
    except (RuntimeError, ConnectionError, TimeoutError) as e:
        where = f"join the Ray cluster at {address}" if address else "start a local Ray"
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise RunError(
            f"could not {where}: {first}. Nothing was written; on a loaded machine try again "
            "(Ray's node start-up timed out), or use executor.kind=inline"
        ) from None
    signals.reinstall()  # ray.init replaced our SIGTERM handler with one that aborts


def alive_nodes() -> list[dict[str, float]]:
    """Total resources of each node that is up (``ray.nodes()``), with its id as ``_id``."""
    import ray

    return [
        {**n["Resources"], "_id": n["NodeID"]}  # type: ignore[dict-item]
        for n in ray.nodes()
        if n.get("Alive")
    ]


def _fits(node: dict[str, float], demand: dict[str, float]) -> int:
    """How many actors with ``demand`` one node can hold."""
    counts = [math.floor(node.get(k, 0.0) / v + _EPS) for k, v in demand.items() if v > 0]
    return min(counts) if counts else 0


def describe(nodes: Iterable[dict[str, Any]], keys: Iterable[str] = ("CPU", "GPU")) -> str:
    nodes = list(nodes)
    keys = list(dict.fromkeys([*keys]))
    total = {k: sum(float(n.get(k, 0.0)) for n in nodes) for k in keys}
    per_node = "; ".join(", ".join(f"{k} {float(n.get(k, 0.0)):g}" for k in keys) for n in nodes)
    return (
        f"{len(nodes)} node(s) with "
        + ", ".join(f"{k} {v:g}" for k, v in total.items())
        + (f" (per node: {per_node})" if len(nodes) > 1 else "")
    )


def check_capacity(ex: ExecutorConfig, nodes: list[dict[str, Any]]) -> None:
    """Refuse a run whose actors cannot all be placed on ``nodes``: with a shared policy, the
    policy actors first (on what they need: GPUs), then the episode actors on what is left."""
    left = [dict(n) for n in nodes]
    for what, count, demand in ex.actor_groups():
        _check_group(ex, left, what, count, demand)
        _take(left, count, {k: v for k, v in demand.items() if v > 0})


def _take(nodes: list[dict[str, Any]], count: int, demand: dict[str, float]) -> None:
    """Subtract ``count`` actors of ``demand`` from ``nodes``, first fit."""
    for node in nodes:
        while count and _fits(node, demand) > 0:
            for k, v in demand.items():
                node[k] = float(node.get(k, 0.0)) - v
            count -= 1


def _check_group(
    ex: ExecutorConfig, nodes: list[dict[str, Any]], what: str, count: int, demand: dict[str, float]
) -> None:
    demand = {k: v for k, v in demand.items() if v > 0}
    keys = ["CPU", "GPU", *ex.resources]
    has = describe(nodes, keys)
    ask = ", ".join(f"{k} {v:g}" for k, v in demand.items())
    share = f" (executor.actors_per_gpu={ex.actors_per_gpu})" if ex.actors_per_gpu else ""
    for k, v in demand.items():
        if not any(float(n.get(k, 0.0)) + _EPS >= v for n in nodes):
            total = sum(float(n.get(k, 0.0)) for n in nodes)
            what = "GPUs" if k == "GPU" else f"{k!r}"
            raise ConfigError(
                f"executor: one actor asks for {k} {v:g}{share if k == 'GPU' else ''} but no node "
                f"has that much ({what}: {total:g} in the whole cluster); the cluster has {has}. "
                + _hint(k)
            )
    fit = sum(_fits(n, demand) for n in nodes)
    if fit < count:
        need = {k: v * count for k, v in demand.items()}
        short = [
            k for k in demand if need[k] > sum(float(n.get(k, 0.0)) for n in nodes) + _EPS
        ] or list(demand)
        k = "GPU" if "GPU" in short else short[0]
        after = (
            " (after the policy actors)"
            if what == "executor.workers" and isinstance(ex, SharedExecutor)
            else ""
        )
        raise ConfigError(
            f"{what}={count} actors of {{{ask}}}{share if k == 'GPU' else ''} "
            f"need {k} {need[k]:g}, but the cluster has {has}{after}: at most {fit} such "
            f"actor(s) fit. Lower {what}"
            + (", raise executor.actors_per_gpu" if k == "GPU" else "")
            + ", or add nodes"
        )
    log.info("Ray cluster: %s; %d actor(s) of {%s}", has, count, ask)


def _hint(resource: str) -> str:
    if resource == "GPU":
        return (
            "Run on GPU nodes, share a GPU between actors (executor.actors_per_gpu), or set "
            "executor.gpus_per_worker=0"
        )
    if resource == "CPU":
        return "Lower executor.cpus_per_worker"
    return f"Start nodes with --resources='{{\"{resource}\": N}}' or drop executor.resources.{resource}"
