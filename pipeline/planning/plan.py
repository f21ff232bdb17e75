"""A run's plan: its config, run dir, tasks, the stages' episode grids
(:class:`pipeline.planning.grid.SpecGrid`), and what the pre-flight settled."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.planning.grid import Chain, SpecGrid
from workers.envs.base import TaskSpec
from workers.episode.rows import WorkerSpec

if TYPE_CHECKING:
    from pipeline.planning.checkpoint_fit import Fit
    from pipeline.planning.config import RunConfig


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
