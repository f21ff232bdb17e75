"""The episodes of a run as a lazy grid: cells x tasks x episode indices, in constant memory.

A plan of a paper-sized grid has hundreds of thousands of episodes; :class:`SpecGrid` is a
``Sequence[EpisodeSpec]`` that makes the spec at an index when asked (the scheduler walks it
once, skipping stored keys), so a large run starts without building them all. Order: cell by
cell, task by task, episode by episode, as every cell sees the same tasks and episodes.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, overload

from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig

from workers.envs.base import TaskSpec
from workers.episode.rows import EpisodeSpec, WorkerSpec

if TYPE_CHECKING:
    from pipeline.planning.checkpoint_fit import Fit
    from pipeline.planning.config import RunConfig


@dataclass(frozen=True)
class CellPlan:
    cell_id: str
    idr: RefinerConfig
    intervention: InterventionConfig
    # after calibration: tau per suite, set on each task's specs (None: idr.tau as it is)
    tau_by_suite: Mapping[str, float] | None = None


@dataclass(frozen=True)
class SpecGrid(Sequence[EpisodeSpec]):
    run_id: str
    cells: tuple[CellPlan, ...]
    tasks: tuple[TaskSpec, ...]
    episodes_per_task: int
    seed: int
    backbone: str
    code_version: str | None = None
    # index of the first episode (held-out calibration episodes start past the evaluated ones)
    first_episode: int = 0
    _n: int = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        n = len(self.cells) * len(self.tasks) * self.episodes_per_task
        object.__setattr__(self, "_n", n)

    def __len__(self) -> int:
        return self._n

    def _spec(self, i: int) -> EpisodeSpec:
        per_cell = len(self.tasks) * self.episodes_per_task
        c, rest = divmod(i, per_cell)
        t, e = divmod(rest, self.episodes_per_task)
        cell, task = self.cells[c], self.tasks[t]
        idr = cell.idr
        if cell.tau_by_suite is not None:
            idr = dataclasses.replace(idr, tau=float(cell.tau_by_suite[task.suite or ""]))
        return EpisodeSpec(
            run_id=self.run_id,
            cell_id=cell.cell_id,
            idr=idr,
            intervention=cell.intervention,
            task=task,
            episode_index=self.first_episode + e,
            seed=self.seed,
            backbone=self.backbone,
            code_version=self.code_version,
        )

    @overload
    def __getitem__(self, i: int) -> EpisodeSpec: ...
    @overload
    def __getitem__(self, i: slice) -> list[EpisodeSpec]: ...
    def __getitem__(self, i: int | slice) -> EpisodeSpec | list[EpisodeSpec]:
        if isinstance(i, slice):
            return [self._spec(j) for j in range(*i.indices(self._n))]
        if i < 0:
            i += self._n
        if not 0 <= i < self._n:
            raise IndexError(i)
        return self._spec(i)

    def __iter__(self) -> Iterator[EpisodeSpec]:
        return (self._spec(i) for i in range(self._n))

    def replace(self, **changes: object) -> SpecGrid:
        return dataclasses.replace(self, **changes)  # type: ignore[arg-type]


@dataclass(frozen=True)
class Chain(Sequence[EpisodeSpec]):
    """Several spec sequences read as one (a run's stages, for counting and listing)."""

    parts: tuple[Sequence[EpisodeSpec], ...]

    def __len__(self) -> int:
        return sum(len(p) for p in self.parts)

    def __getitem__(self, i: int) -> EpisodeSpec:  # type: ignore[override]
        if i < 0:
            i += len(self)
        for p in self.parts:
            if i < len(p):
                return p[i]
            i -= len(p)
        raise IndexError(i)

    def __iter__(self) -> Iterator[EpisodeSpec]:
        for p in self.parts:
            yield from p


def planned_numerics(cfg: RunConfig) -> str:
    """The numerical path ``cfg`` runs on (workers.policy.forward_shape.numerics_label), known
    before any backbone is built: a backbone that turns out not to batch says ``per_pass`` in its
    rows."""
    from workers.backbones.factory import backbone_class
    from workers.policy.forward_shape import numerics_label

    ex = cfg.executor
    remote = bool(getattr(backbone_class(cfg.backbone.kind), "remote", False))
    batched = cfg.backbone.batched is not False
    return numerics_label(ex.forward_shape(), ex.threads(), batched, remote)


@dataclass
class RunPlan:
    cfg: RunConfig
    run_dir: Path
    run_id: str
    tasks: list[TaskSpec]
    specs: SpecGrid  # the first stage (lazy: made when the scheduler reaches them)
    worker_spec: WorkerSpec
    calibrated: SpecGrid  # scheduled after tau calibration, with tau filled in then
    code_version: str = ""
    checkpoint: dict[str, object] | None = None  # pipeline.planning.provenance.checkpoint_record
    fit: Fit | None = None  # what the pre-flight settled (pipeline.planning.checkpoint_fit)
    env_server: dict[str, object] | None = None  # the env server's hello (python, version)
    numerics: str = ""  # the numerical path the config asks for (workers.policy.forward_shape)
    # this host's hardware record (workers.hardware.hardware_record), for run.json; None on a
    # cluster, where the actors' rows say what ran
    hardware: dict[str, object] | None = None
    # the diagnose cells on the held-out episodes that fit tau (a calibration: block), run
    # into RUN_DIR/calibration_episodes before the calibrated cells; None: tau is fitted on
    # the evaluated episodes
    held_out: SpecGrid | None = None
    held_out_record: dict[str, object] | None = None  # calibration.held_out_record

    def all_specs(self) -> Chain:
        """The evaluated episodes (the held-out calibration episodes are not among them)."""
        return Chain((self.specs, self.calibrated))

    def held_out_count(self) -> int:
        return len(self.held_out) if self.held_out is not None else 0
