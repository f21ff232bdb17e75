"""What the driver sends to an actor (EpisodeSpec, WorkerSpec) and what comes back (typed rows).

This module owns the row format. ``EpisodeRow`` and ``StepRow`` are the columns of the
episodes and steps tables, in order; ``pipeline.results.store`` derives the Parquet schemas from them
(field types map to Arrow types; ``F32`` marks a float stored as float32). Every row of an
episode, the actor's own or the error row the scheduler stores for an actor that died under
it, starts from :meth:`EpisodeRow.from_spec`, so the columns a spec determines agree wherever
a row is made. Only plain, picklable data crosses the driver/actor boundary; actors never
write files.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Annotated, Any

from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig

from workers.envs.base import TaskSpec
from workers.envs.server.spec import ServerSpec

F32 = Annotated[float, "float32"]  # a float stored as float32 (step tables are large)


@dataclass(frozen=True)
class WorkerSpec:
    """What an actor loads once: the backbone and the env (bundled, not passed as kwargs).

    ``backbone_kind`` / ``env_suite`` are registered names or ``"package.module:Class"``."""

    backbone_kind: str
    backbone_params: dict[str, Any]
    env_suite: str
    env_params: dict[str, Any]
    replan_steps: int | None = 4  # actions executed per inference; None: the whole chunk
    batched: bool | None = None
    env_server: ServerSpec | None = None  # the env runs in an env server started from this
    # shared policy: the policy actor (a Ray handle) this actor sends its inferences to;
    # None: the actor holds the backbone itself
    policy_actor: Any = None
    envs_per_worker: int = 1  # envs an actor holds (> 1 only with a shared policy)
    log_dir: str | None = None  # where a Ray actor writes its output (workers.worker_log)
    # the run's perturbations (``none`` / ``kind:severity``): the env's tasks crossed with them
    perturbations: tuple[str, ...] = ()
    # the forward's shape (workers.policy.forward_shape): rows per forward (in-actor: None, each
    # inference's own; shared: rows, or "dynamic") and torch's CPU threads (None: unchanged)
    forward_rows: int | str | None = None
    torch_threads: int | None = None
    # set in the actor's process before anything computes (workers.hardware.numerics_env:
    # executor.numerics_mode portable pins the instruction sets); empty: the host's own
    numerics_env: dict[str, str] = field(default_factory=dict)
    # episode videos (workers.episode.videos): the first N episodes of each task and cell, into
    # video_dir; 0: none
    video_episodes: int = 0
    video_camera: str | None = None
    video_fps: float | None = None
    video_dir: str | None = None
    # shared policy on the socket transport: where the policy actors listen, the run's token and
    # the socket's limits (workers.policy.socket_settings.SocketSettings); None: no socket
    policy_socket: Any = None


@dataclass(frozen=True)
class EpisodeSpec:
    """One episode of one cell; (cell_id, task_id, episode_index) is its key.

    It carries the whole ``TaskSpec`` (suite, name, step budget) and the backbone's name, so
    that any row of this episode can be made from the spec alone (see EpisodeRow.from_spec)."""

    run_id: str
    cell_id: str
    idr: RefinerConfig
    intervention: InterventionConfig
    task: TaskSpec  # its ``suite`` is set (the env's suite name where the task names none)
    episode_index: int
    seed: int
    backbone: str  # the backbone as named in the config (backbone.kind)
    attempt: int = 1
    code_version: str | None = None

    @property
    def task_id(self) -> str:
        return self.task.task_id

    @property
    def key(self) -> tuple[str, str, int]:
        return (self.cell_id, self.task_id, self.episode_index)

    def retry(self) -> EpisodeSpec:
        return dataclasses.replace(self, attempt=self.attempt + 1)


@dataclass(slots=True, kw_only=True)
class EpisodeRow:
    """One row of the episodes table (field order = column order)."""

    run_id: str
    cell_id: str
    mode: str
    guidance: str
    strategy: str
    alpha: float
    beta: float
    lam: float
    tau: float
    backbone: str
    suite: str
    task_id: str
    task_name: str
    # the perturbation the task runs under (kind and severity; "none": unperturbed). Rows of
    # run dirs written before these columns existed hold nulls: the aggregation reads their
    # task ids (task@kind:severity) instead
    perturbation: str | None = None
    severity: float | None = None
    instruction: str | None = None
    episode_index: int
    seed: int
    init_state_id: str | None = None
    success: bool = False
    steps: int = 0
    success_step: int | None = None
    max_steps: int
    subtasks_done: int = 0
    subtasks_total: int
    # failed episodes (error rows excluded): a code (timeout, or the env's own, e.g. the
    # tabletop chain's wrong_order / subtask_budget) and the env's words for it
    failure: str | None = None
    failure_detail: str | None = None
    sim_seconds: float = 0.0
    wall_seconds: float | None = None
    inference_ms_mean: float | None = None
    gate_rate: float | None = None
    e_img_mean: float | None = None
    e_prop_mean: float | None = None
    r_img_mean: float | None = None
    error: str | None = None  # set: the episode did not finish (never a task failure)
    attempt: int = 1
    worker: str | None = None
    node: str | None = None  # HOSTNAME/RAY_NODE_ID of the actor (inline: the hostname)
    render_backend: str | None = None
    # the numerical path that produced the episode (workers.policy.forward_shape.numerics_label):
    # episodes with one label, config and seed have the same actions bit for bit
    numerics: str | None = None
    # the hardware class that produced it (workers.hardware): the CPU model and the instruction
    # set torch dispatches to, and the GPU where the model computes on one. Numerics are equal
    # across episodes with one (numerics, hardware) pair; null in run dirs made before it existed
    hardware: str | None = None
    crn: bool | None = None
    started_at: str | None = None
    finished_at: str | None = None
    code_version: str | None = None

    @classmethod
    def from_spec(cls, spec: EpisodeSpec, **values: Any) -> EpisodeRow:
        """The row of ``spec`` with every column the spec determines (SPEC_COLUMNS) filled in;
        ``values`` sets the others (the outcome, the worker, timing)."""
        task = spec.task
        return cls(
            run_id=spec.run_id,
            cell_id=spec.cell_id,
            mode=spec.idr.mode,
            guidance=spec.idr.guidance,
            strategy=spec.intervention.strategy,
            alpha=spec.idr.alpha,
            beta=spec.idr.beta,
            lam=spec.idr.lam,
            tau=spec.idr.tau,
            backbone=spec.backbone,
            suite=task.suite or "",
            task_id=task.task_id,
            task_name=task.name,
            perturbation=task.perturbation or "none",
            severity=task.severity,
            episode_index=spec.episode_index,
            seed=spec.seed,
            max_steps=task.max_steps,
            subtasks_total=task.subtasks_total,
            attempt=spec.attempt,
            code_version=spec.code_version,
            **values,
        )

    @classmethod
    def error_row(cls, spec: EpisodeSpec, reason: str, **values: Any) -> EpisodeRow:
        """The row stored for an episode that did not finish: an exception inside it, or an
        actor that died or timed out under it. Never counted as a task failure."""
        return cls.from_spec(spec, error=reason, **values)

    @property
    def key(self) -> tuple[str, str, int]:
        return (self.cell_id, self.task_id, self.episode_index)


# Episode columns fixed by the EpisodeSpec alone (the same in an actor's row and an error row).
SPEC_COLUMNS = (
    "run_id",
    "cell_id",
    "mode",
    "guidance",
    "strategy",
    "alpha",
    "beta",
    "lam",
    "tau",
    "backbone",
    "suite",
    "task_id",
    "task_name",
    "perturbation",
    "severity",
    "episode_index",
    "seed",
    "max_steps",
    "subtasks_total",
    "attempt",
    "code_version",
)


@dataclass(slots=True, kw_only=True)
class StepRow:
    """One row of the steps table: one inference (field order = column order)."""

    run_id: str
    cell_id: str
    task_id: str
    episode_index: int
    inference_index: int
    step: int  # env step at which the chunk was predicted
    e_img: F32 | None = None
    e_prop: F32 | None = None
    r_img: F32 | None = None
    gate: F32 | None = None
    w_prop: F32 | None = None
    action_base: list[F32] = field(default_factory=list)  # first action of the base chunk
    action_final: list[F32] = field(default_factory=list)  # first action executed
    gripper: F32 | None = None
    inference_ms: F32 | None = None  # the forwards and the method's arithmetic (pcd: its render)
    # what the inference cost: rows of the base's forward its method's passes took (3 for
    # IDR at batch 1), and env steps executed from its chunk (null in older run dirs)
    pass_rows: int | None = None
    executed_steps: int | None = None


@dataclass
class EpisodeResult:
    episode: EpisodeRow  # one row of the episodes table
    steps: list[StepRow]  # rows of the steps table (one per inference)
    # the worker may be broken after this episode (it ran out of memory): replace it
    unhealthy: bool = False

    @property
    def key(self) -> tuple[str, str, int]:
        return self.episode.key

    @property
    def is_error(self) -> bool:
        return self.episode.error is not None
