"""What the actors of a run are given and run on: the WorkerSpec every worker builds from (the
backbone, the env or its server, how it executes), the shared policy's sockets and the run's
token for them, and the hardware record of the host whose actors run the episodes."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.execution.preflight import perturbations_of
from pipeline.planning.config import RunConfig
from pipeline.planning.executor_config import SharedExecutor
from pipeline.planning.plan import RunPlan
from pipeline.rundir import LOGS_DIR, VIDEOS_DIR, policy_token
from workers.episode.rows import WorkerSpec
from workers.hardware import numerics_env

if TYPE_CHECKING:
    from pipeline.planning.checkpoint_fit import Fit
    from workers.envs.base import TaskSpec
    from workers.envs.server.spec import ServerSpec
    from workers.policy.socket_settings import SocketSettings


def host_hardware(cfg: RunConfig) -> dict[str, object] | None:
    """This host's hardware record where this host's actors run the episodes (a local Ray or
    inline); None where a cluster's nodes do (executor.address)."""
    if cfg.executor.kind == "ray" and cfg.executor.address:
        return None
    device = cfg.backbone.params.get("device") if cfg.backbone.kind != "remote" else None
    from workers.hardware import (
        apply_numerics_env,
        hardware_record,
        numerics_env_for_now,
        renderer_in_child,
    )

    # the actors set the mode's pins first thing; the record is taken as they will see it. An
    # inline executor's actor is this process, so the pins stay; Ray's actors are processes of
    # their own, and this one (a test session, a notebook) and what it starts later keep their
    # environment
    pins = numerics_env(cfg.executor.numerics_mode)
    if cfg.executor.kind == "inline":
        apply_numerics_env(pins)
        record = hardware_record(device)
    else:
        with numerics_env_for_now(pins):
            record = hardware_record(device)
    record["renderer"] = renderer_in_child()
    return record


def build_worker_spec(
    cfg: RunConfig, fit: Fit, server: ServerSpec | None, run_dir: Path, tasks: list[TaskSpec]
) -> WorkerSpec:
    """What every worker builds: the backbone, the env (or its server), how it executes."""
    backbone_params = dict(cfg.backbone.params)
    if isinstance(backbone_params.get("path"), str) and Path(backbone_params["path"]).exists():
        # actors may run in another working directory (or on another node with the same layout)
        backbone_params["path"] = str(Path(backbone_params["path"]).resolve())
    return WorkerSpec(
        cfg.backbone.kind,
        backbone_params,
        cfg.env.suite,
        cfg.env.params,
        None if fit.replan_steps == "chunk" else int(fit.replan_steps),
        cfg.backbone.batched,
        server,
        envs_per_worker=cfg.executor.episodes_per_actor(),
        log_dir=str((run_dir / LOGS_DIR).resolve()),
        perturbations=perturbations_of(tasks),
        forward_rows=cfg.executor.forward_shape(),
        torch_threads=cfg.executor.threads(),
        numerics_env=numerics_env(cfg.executor.numerics_mode),
        video_episodes=cfg.videos.episodes,
        video_camera=cfg.videos.camera,
        video_fps=cfg.videos.fps,
        video_dir=str((run_dir / VIDEOS_DIR).resolve()),
        policy_socket=policy_socket(cfg, run_dir),
    )


def policy_socket(cfg: RunConfig, run_dir: Path) -> SocketSettings | None:
    """A shared policy's sockets (``executor.policy_transport=socket``): loopback on a local
    Ray, the node's address on a cluster (``executor.address``); frames bounded by what the env
    renders and takes, connections by the episodes in flight. The run's token is added when the
    run starts (:func:`with_policy_token`: planning writes nothing). None: no socket."""
    ex = cfg.executor
    if not isinstance(ex, SharedExecutor) or ex.policy_transport != "socket":
        return None
    from pipeline.planning.checkpoint_fit import describe_env
    from workers.policy.socket_settings import (
        DEFAULT_IDLE_S,
        SocketLimits,
        SocketSettings,
        connection_cap,
        frame_bound,
    )

    try:
        env = describe_env(cfg.env.suite, cfg.env.params)
    except ValueError:  # the pre-flight said so already; the default bound stands
        env = None
    limits = SocketLimits(
        max_frame=frame_bound(env),
        max_connections=ex.policy_connections or connection_cap(ex.episodes_per_policy_actor()),
        idle_timeout_s=ex.policy_idle_s or ex.episode_timeout_s or DEFAULT_IDLE_S,
    )
    host = None if ex.kind == "ray" and ex.address else "127.0.0.1"
    return SocketSettings(host, None, limits)


def with_policy_token(plan: RunPlan) -> RunPlan:
    """The plan with its run's policy-socket token (``RUN_DIR/policy.token``, mode 0600, made
    on the run's first start and kept for its resumes), where the run opens policy sockets."""
    settings = plan.worker_spec.policy_socket
    if settings is None:
        return plan
    from workers.policy.socket_settings import SocketToken

    token = SocketToken(policy_token(plan.run_dir))
    spec = replace(plan.worker_spec, policy_socket=replace(settings, token=token))
    return replace(plan, worker_spec=spec)
