"""What the driver sends to an actor (EpisodeSpec, WorkerSpec) and what comes back (rows).

Only plain, picklable data crosses the driver/actor boundary. The actor returns one episode
row and its step rows as dicts whose keys are the Parquet schemas' columns
(``pipeline.store``); it never writes files.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from workers.idr import IDRConfig
from workers.interventions import InterventionConfig


@dataclass(frozen=True)
class WorkerSpec:
    """What an actor loads once: the backbone and the env (bundled, not passed as kwargs)."""

    backbone_kind: str
    backbone_params: dict[str, Any]
    env_suite: str
    env_params: dict[str, Any]
    replan_steps: int = 4
    batched: bool | None = None


@dataclass(frozen=True)
class EpisodeSpec:
    """One episode of one cell; (cell_id, task_id, episode_index) is its key."""

    run_id: str
    cell_id: str
    idr: IDRConfig
    intervention: InterventionConfig
    task_id: str
    episode_index: int
    seed: int
    attempt: int = 1
    meta: dict[str, Any] = field(default_factory=dict)  # copied into the episode row

    @property
    def key(self) -> tuple[str, str, int]:
        return (self.cell_id, self.task_id, self.episode_index)

    def row_head(self, backbone: str, suite: str) -> dict[str, Any]:
        """The episode-row columns this spec determines (the actor adds the outcome)."""
        return {
            "run_id": self.run_id,
            "cell_id": self.cell_id,
            "mode": self.idr.mode,
            "guidance": self.idr.guidance,
            "strategy": self.intervention.strategy,
            "alpha": self.idr.alpha,
            "beta": self.idr.beta,
            "lam": self.idr.lam,
            "tau": self.idr.tau,
            "backbone": backbone,
            "suite": suite,
            "task_id": self.task_id,
            "episode_index": self.episode_index,
            "seed": self.seed,
            "success": False,
            "attempt": self.attempt,
            **self.meta,
        }

    def retry(self) -> EpisodeSpec:
        return EpisodeSpec(
            self.run_id,
            self.cell_id,
            self.idr,
            self.intervention,
            self.task_id,
            self.episode_index,
            self.seed,
            self.attempt + 1,
            self.meta,
        )


@dataclass
class EpisodeResult:
    episode: dict[str, Any]  # one row of the episodes table
    steps: list[dict[str, Any]]  # rows of the steps table (one per inference)
    # the worker may be broken after this episode (it ran out of memory): replace it
    unhealthy: bool = False

    @property
    def key(self) -> tuple[str, str, int]:
        e = self.episode
        return (e["cell_id"], e["task_id"], e["episode_index"])

    @property
    def is_error(self) -> bool:
        return self.episode.get("error") is not None
