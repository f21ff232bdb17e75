"""The episode worker: one backbone wrapped by IDR and one env, loaded once, many episodes.

``EpisodeWorker`` is a plain class, testable without Ray; ``RayEpisodeWorker`` is the thin
remote wrapper the scheduler starts (Ray is imported lazily). Switching the IDR cell between
episodes does not reload the backbone. An exception inside an episode becomes an error row
(``error`` set), never a task failure and never an exception that would kill the actor.
"""

from __future__ import annotations

import logging
import os
import queue
import socket
import sys
import time
import traceback
import zlib
from collections import deque
from dataclasses import dataclass, field
from datetime import UTC, datetime
from typing import Any

import numpy as np
from idr_core.tensors import is_torch

from workers.backbones.base import backbone_member
from workers.envs.base import EpisodeStatus, episode_status, suite_info
from workers.envs.server.client import EnvServerError
from workers.episode.rows import EpisodeResult, EpisodeRow, EpisodeSpec, StepRow, WorkerSpec

log = logging.getLogger(__name__)

MAX_SERVER_RESTARTS = 2  # env server deaths under one episode before it becomes an error row
DIAGNOSTICS = ("e_img", "e_prop", "r_img", "gate", "w_prop")  # per-inference, from the refiner


class NonFiniteActionError(RuntimeError):
    """The backbone (or the refiner) produced NaN/inf; the step was not sent to the simulator."""


class NonFiniteStateError(RuntimeError):
    """The env returned a NaN/inf state (a diverged simulation); the episode is not scored."""


def step_seed(seed: int, task_id: str, episode_index: int, inference_index: int) -> int:
    """Per-inference seed shared by all cells (paired comparisons see the same noise)."""
    ss = np.random.SeedSequence(
        [seed, zlib.crc32(task_id.encode()), episode_index, inference_index]
    )
    return int(ss.generate_state(1)[0])


def _now() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def _to_numpy(x: Any) -> np.ndarray:
    if is_torch(x):
        return x.detach().float().cpu().numpy()
    return np.asarray(x, dtype=np.float32)


@dataclass
class _Rollout:
    """What an episode's rollout has gathered so far."""

    obs: Any  # the env's last observation
    status: Any = None  # its EpisodeStatus (workers.envs.base)
    steps: list[StepRow] = field(default_factory=list)  # one row per inference
    success_step: int | None = None  # the first step at which the env said success
    crn: Any = None  # the last inference's common-random-numbers flag
    video: Any = None  # workers.episode.videos.EpisodeVideo of a recorded episode
    ensemble: Any = None  # temporal ensembling's averager (lerobot_policy_idr.runtime)
    frames: Any = None  # a history-fed base's last frames (policy observations), every env step


class EpisodeWorker:
    """Holds a backbone + IDR wrapper and an env; runs one episode per call."""

    def __init__(self, spec: WorkerSpec) -> None:
        from workers.rendering import configure_rendering
        from workers.worker_log import log_to_file

        log_to_file(spec.log_dir, "worker")  # its output in the run dir, not on the terminal
        from workers.hardware import apply_numerics_env

        apply_numerics_env(spec.numerics_env)  # before anything computes or renders
        self.spec = spec
        self.render_backend = configure_rendering()
        # Imported after the rendering backend is set: env modules may import MuJoCo.
        from workers.backbones.factory import make_backbone
        from workers.envs.factory import make_env
        from workers.policy.forward_shape import fix_forward_shape, set_torch_threads
        from workers.policy.wrapper import IDRWrapper

        if spec.policy_actor is not None:  # shared: the model lives in a policy actor
            from workers.policy.actor import connect

            self.backbone = None
            self.policy: Any = connect(spec.policy_actor)
            info = self.policy.info
            self.cameras = info["cameras"]
            self.history_steps = int(info.get("history_steps") or 1)
            self.numerics = info["numerics"]
            self.hardware = info.get("hardware")
        else:
            set_torch_threads(spec.torch_threads)
            self.backbone = make_backbone(spec.backbone_kind, spec.backbone_params)
            self.policy = IDRWrapper(self.backbone, batched=spec.batched)
            self.numerics = fix_forward_shape(self.policy, spec.forward_rows, spec.torch_threads)
            self.cameras = backbone_member(self.backbone, "cameras")  # None: all the env has
            self.history_steps = int(backbone_member(self.backbone, "history_steps"))
            from workers.hardware import hardware_class, hardware_record

            device = (spec.backbone_params or {}).get("device")
            self.hardware = hardware_class(hardware_record(device))
        self.env = make_env(spec.env_suite, spec.env_params, spec.env_server, spec.perturbations)
        # shared policy: more envs, each episode on one of them in its own thread (Ray runs up
        # to envs_per_worker calls at once), so one env steps while another's request is away
        self._envs: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._all_envs = [self.env]
        for _ in range(spec.envs_per_worker - 1):
            self._all_envs.append(
                make_env(spec.env_suite, spec.env_params, spec.env_server, spec.perturbations)
            )
        for env in self._all_envs:
            self._envs.put(env)
        # an env with its own renderer (PyBullet...) says so; MuJoCo envs use the worker's
        self.render_backend = suite_info(self.env).render_backend or self.render_backend
        self.tasks = {t.task_id: t for t in self.env.tasks()}
        self.worker_id = f"{socket.gethostname()}:{os.getpid()}"
        self.node = current_node()

    def ping(self) -> str:
        return self.worker_id

    def run_episode(self, spec: EpisodeSpec) -> EpisodeResult:
        started, t0 = _now(), time.perf_counter()
        where = {
            "worker": self.worker_id,
            "node": self.node,
            "render_backend": self.render_backend,
            "numerics": self.numerics,
            "hardware": self.hardware,
        }
        env = self._envs.get()
        try:
            steps, outcome = self._rollout_restarting(spec, env)
            row = EpisodeRow.from_spec(spec, **outcome, **where)
            unhealthy = False
        except Exception as exc:
            steps = []
            tb = traceback.format_exception(exc)
            reason = f"{type(exc).__name__}: {exc}\n{''.join(tb[-3:])}"[:4000]
            row = EpisodeRow.error_row(spec, reason, **where)
            # out of memory: this process may be left broken; the scheduler replaces the worker
            unhealthy = isinstance(exc, MemoryError)
        finally:
            self._envs.put(env)
        row.started_at, row.finished_at = started, _now()
        row.wall_seconds = time.perf_counter() - t0
        return EpisodeResult(row, steps, unhealthy=unhealthy)

    def _rollout_restarting(
        self, spec: EpisodeSpec, env: Any
    ) -> tuple[list[StepRow], dict[str, Any]]:
        """The rollout; when the env server dies or hangs under it (a fault of this actor's
        machinery, not of the episode), the server is restarted and the episode run again from
        its reset, up to MAX_SERVER_RESTARTS times per episode."""
        for restart in range(MAX_SERVER_RESTARTS + 1):
            try:
                return self._rollout(spec, env)
            except EnvServerError as exc:
                if restart == MAX_SERVER_RESTARTS:
                    raise
                log.warning(
                    "episode %s: %s; restarting the env server and running the episode again",
                    spec.key,
                    str(exc).splitlines()[0],
                )
                env.restart()
        raise AssertionError("unreachable")

    def _rollout(self, spec: EpisodeSpec, env: Any) -> tuple[list[StepRow], dict[str, Any]]:
        """Run one episode: infer a chunk, execute ``replan_steps`` of it, until the env is
        done. Returns the step rows and the episode's outcome columns."""
        policy = self.policy
        if self.spec.policy_actor is not None:  # one proxy per episode: threads share the actor
            from workers.policy.actor import PolicyServiceClient

            policy = PolicyServiceClient(
                self.spec.policy_actor, self.policy.endpoint, self.policy.info
            )
        try:
            if spec.task_id not in self.tasks:
                raise ValueError(f"task_id={spec.task_id!r} not in suite {self.spec.env_suite!r}")
            policy.reset()
            ep = _Rollout(obs=env.reset(spec.task_id, spec.episode_index, spec.seed))
            ep.status = episode_status(env, ep.obs)
            if self.history_steps > 1:
                ep.frames = deque(maxlen=self.history_steps)
                self._remember(ep)
            ep.video = self._video(spec, env)
            if ep.video is not None:
                ep.video.add(ep.obs)
            instruction = ep.status.instruction  # the episode's first (CALVIN: one per subtask)
            info = suite_info(env)
            while not ep.status.done:
                chunk = self._infer(policy, env, spec, ep, info.gripper_index)
                ep.steps[-1].executed_steps = self._execute(
                    policy, env, chunk[: self._horizon(spec)], ep, info.policy_reset_per_subtask
                )
            if ep.video is not None:
                ep.video.write()
            return ep.steps, self._outcome(spec, env.control_hz, instruction, ep)
        finally:
            if policy is not self.policy:  # the episode's connection to the policy actor
                policy.close()

    def _video(self, spec: EpisodeSpec, env: Any) -> Any:
        """The episode's video recorder, for the first ``video_episodes`` of a task and cell."""
        s = self.spec
        if spec.episode_index >= s.video_episodes or s.video_dir is None:
            return None
        from workers.episode.videos import EpisodeVideo, video_path

        camera = s.video_camera or env.cameras[0]
        if camera not in env.cameras:
            raise ValueError(f"videos.camera={camera!r}: the env renders {list(env.cameras)}")
        path = video_path(s.video_dir, spec.cell_id, spec.task_id, spec.episode_index)
        return EpisodeVideo(path, camera, s.video_fps or env.control_hz)

    def _remember(self, ep: _Rollout) -> None:
        """The current frame joins a history-fed base's frames (as its own select_action
        queues every step's observation)."""
        from workers.episode.observation import to_policy_observation

        ep.frames.append(to_policy_observation(ep.obs, ep.status.instruction, self.cameras))

    def _horizon(self, spec: EpisodeSpec) -> int | None:
        """Actions executed per inference: the cell's ``horizon``, else the run's replan_steps
        (None: the whole chunk); 1 for a method that infers at every step."""
        from idr_core.methods import method_of

        if method_of(spec.idr).every_step:
            return 1
        return spec.idr.horizon or self.spec.replan_steps

    def _infer(
        self, policy: Any, env: Any, spec: EpisodeSpec, ep: _Rollout, gripper_index: int | None
    ) -> np.ndarray:
        """One inference on the current observation: its step row appended to ``ep``; the
        chunk to execute (T, D) (temporal ensembling: the averaged action, (1, D))."""
        from idr_core.methods import method_of

        from workers.episode.observation import to_policy_observation

        k = len(ep.steps)  # one row per inference
        method = method_of(spec.idr)
        if ep.frames is not None:  # the current frame and the past ones it travels with
            obs = ep.frames[-1]
            obs.extras.update(past_frames(list(ep.frames)[:-1]))
        else:
            obs = to_policy_observation(ep.obs, ep.status.instruction, self.cameras)
        render_ms = 0.0
        if method.hidden_objects:  # its render is part of the method's cost
            from workers.episode.observation import image_to_tensor
            from workers.policy.wrapper import NO_OBJECTS_KEY

            t0 = time.perf_counter()
            hidden = env.object_hidden_images()
            obs.extras[NO_OBJECTS_KEY] = {cam: image_to_tensor(hidden[cam]) for cam in obs.images}
            render_ms = (time.perf_counter() - t0) * 1e3
        seed = step_seed(spec.seed, spec.task_id, spec.episode_index, k)
        out = policy.infer(obs, seed, spec.idr, spec.intervention)  # the cell's, per request
        ep.crn = out.crn
        chunk = _to_numpy(out.action)[0]
        if method.every_step:  # lerobot's temporal ensembler, then the base's finishing steps
            from lerobot_policy_idr.runtime import TemporalEnsemble

            if ep.ensemble is None:
                ep.ensemble = TemporalEnsemble(spec.idr.te_coeff, chunk.shape[0])
            chunk = _to_numpy(policy.finish(ep.ensemble.update(out.action)))
        base = _to_numpy(out.a_base)[0]
        d = out.diag.to_numpy() if out.diag is not None else {}
        ep.steps.append(
            StepRow(
                run_id=spec.run_id,
                cell_id=spec.cell_id,
                task_id=spec.task_id,
                episode_index=spec.episode_index,
                inference_index=k,
                step=ep.status.steps,
                **{name: float(d[name][0]) for name in DIAGNOSTICS if name in d},
                action_base=base[0].tolist(),
                action_final=chunk[0].tolist(),
                gripper=None if gripper_index is None else float(chunk[0][gripper_index]),
                inference_ms=out.inference_ms + render_ms,
                pass_rows=out.pass_rows,
            )
        )
        return chunk

    def _execute(
        self, policy: Any, env: Any, chunk: np.ndarray, ep: _Rollout, per_subtask: bool
    ) -> int:
        """The actions of ``chunk``, open loop, until the env is done or (``per_subtask``) a
        subtask is: then the policy is reset and the rest dropped. Returns how many ran."""
        subtasks_before = ep.status.subtasks_done
        executed = 0
        for action in chunk:
            if not np.isfinite(action).all():
                raise NonFiniteActionError(
                    f"non-finite action at step {ep.status.steps}: {action.tolist()}; "
                    "not sent to the env"
                )
            ep.obs = env.step(action)
            executed += 1
            ep.status = st = episode_status(env, ep.obs)
            if ep.frames is not None and not st.done:
                self._remember(ep)
            if ep.video is not None:
                ep.video.add(ep.obs)
            if not np.isfinite(ep.obs.state).all():
                raise NonFiniteStateError(
                    f"non-finite state after step {st.steps}: {np.asarray(ep.obs.state).tolist()}; "
                    "the simulation diverged"
                )
            if ep.success_step is None and st.success:
                ep.success_step = st.steps
            if st.done:
                break
            if per_subtask and st.subtasks_done != subtasks_before:
                policy.reset()  # the next subtask is a rollout of its own (CALVIN)
                ep.ensemble = None
                if ep.frames is not None:  # its history starts at its first frame
                    ep.frames = deque([ep.frames[-1]], maxlen=self.history_steps)
                break
        return executed

    def _outcome(
        self, spec: EpisodeSpec, control_hz: float, instruction: str, ep: _Rollout
    ) -> dict[str, Any]:
        """The episode's outcome columns, once the env is done."""

        def mean(name: str) -> float | None:
            vals = [v for s in ep.steps if (v := getattr(s, name)) is not None]
            return float(np.mean(vals)) if vals else None

        st = ep.status
        init_state_id = st.info.init_state_id or f"{spec.seed}/{spec.episode_index}"
        return {
            "instruction": instruction,
            "init_state_id": str(init_state_id),
            "success": bool(st.success),
            "steps": st.steps,
            "success_step": ep.success_step,
            "subtasks_done": st.subtasks_done,
            **episode_failure(st, self.tasks[spec.task_id].max_steps),
            "sim_seconds": st.steps / control_hz,
            "inference_ms_mean": mean("inference_ms"),
            # in diagnose mode: the rate of the gate the full method would have applied
            "gate_rate": mean("gate"),
            "e_img_mean": mean("e_img"),
            "e_prop_mean": mean("e_prop"),
            "r_img_mean": mean("r_img"),
            "crn": ep.crn,
        }

    def close(self) -> None:
        """Idempotent."""
        envs, self._all_envs = getattr(self, "_all_envs", []), []
        self.env = None
        for env in envs:
            env.close()


def past_frames(frames: list[Any]) -> dict[str, Any]:
    """A history-fed base's past frames as request extras (``workers.backbones.base``):
    camera -> (1, k, 3, H, W) and (1, k, S), oldest first; nothing at an episode's start."""
    import torch

    from workers.backbones.base import HISTORY_IMAGES, HISTORY_STATE

    if not frames:
        return {}
    return {
        HISTORY_IMAGES: {
            cam: torch.stack([f.images[cam] for f in frames], dim=1) for cam in frames[0].images
        },
        HISTORY_STATE: torch.stack([f.state for f in frames], dim=1),
    }


def episode_failure(status: EpisodeStatus, max_steps: int) -> dict[str, str | None]:
    """Why a finished episode failed: the env's own cause where it ends episodes early
    (``failure_cause`` / ``failure_reason``, e.g. the tabletop chain's wrong_order), else
    ``timeout`` (the step budget ran out). Both None for a success."""
    if status.success:
        return {"failure": None, "failure_detail": None}
    episode = status.info
    if episode.failure_cause:
        return {"failure": str(episode.failure_cause), "failure_detail": episode.failure_reason}
    if status.steps >= max_steps:
        return {"failure": "timeout", "failure_detail": f"no success within {max_steps} steps"}
    return {
        "failure": "ended",
        "failure_detail": f"the env ended the episode at step {status.steps}",
    }


def remote_worker_class(
    num_cpus: float,
    num_gpus: float,
    resources: dict[str, float] | None = None,
    placement: str = "default",
    concurrency: int = 1,
) -> Any:
    """The Ray actor class wrapping EpisodeWorker (Ray imported here, lazily): ``num_gpus`` may
    be a fraction (actors sharing a GPU), ``resources`` custom Ray resources per actor,
    ``placement`` ``spread`` for Ray's SPREAD scheduling strategy."""
    import ray

    return ray.remote(
        num_cpus=num_cpus,
        num_gpus=num_gpus,
        resources=dict(resources) if resources else None,
        scheduling_strategy="SPREAD" if placement == "spread" else "DEFAULT",
        max_restarts=0,
        max_concurrency=concurrency,  # envs_per_worker episodes at once (threads)
    )(EpisodeWorker)


def current_node() -> str:
    """Where this worker runs: ``HOSTNAME/RAY_NODE_ID`` inside a Ray actor (several nodes can
    share a host), the hostname elsewhere (the inline executor). Under Slurm the node's Slurm
    name stands for the hostname (several slurmd can share a host too)."""
    from workers.worker_log import in_ray_actor

    host = os.environ.get("SLURMD_NODENAME") or socket.gethostname()
    if in_ray_actor():
        try:
            return f"{host}/{sys.modules['ray'].get_runtime_context().get_node_id()}"
        except Exception:  # an old or partial Ray: the hostname still says where
            pass
    return host
