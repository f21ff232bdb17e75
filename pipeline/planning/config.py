"""Run configuration: typed, validated before any work starts, saved with every run.

A config is YAML (see ``conf/``) validated by pydantic models that forbid unknown keys.
Command-line overrides are dotted ``key=value`` pairs whose values are parsed as YAML
(``executor.workers=4``, ``grid=[{mode: [baseline, E]}]``). Every validation error names
the field and what is allowed, in one message (:class:`ConfigError`).
"""

from __future__ import annotations

import difflib
import hashlib
import json
import re
import typing
from pathlib import Path
from typing import Any, Literal

import yaml
from idr_core.interventions import SPACES, STRATEGIES
from idr_core.refiner import GUIDANCES, MODES
from pydantic import (
    BaseModel,
    Field,
    ValidationError,
    field_serializer,
    field_validator,
    model_validator,
)

from pipeline.errors import ConfigError
from pipeline.planning.config_model import StrictModel
from pipeline.planning.config_yaml import NoAliasDumper, apply_overrides, safe_load_yaml
from pipeline.planning.executor_config import (
    ExecutorConfig,
    InActorExecutor,
    without_ignored_keys,
)
from pipeline.planning.grid import INTERVENTION_KEYS, Cell, expand_grid
from pipeline.planning.refiner_settings import RefinerSettings

DEFAULT_REPLAN_STEPS = 4  # actions per inference where neither the config nor the env says


class BackboneConfig(StrictModel):
    kind: str = Field(description="backbone type, e.g. fake_marker, lerobot")
    params: dict[str, Any] = Field(default_factory=dict, description="passed to the backbone")
    replan_steps: int | Literal["chunk"] | None = Field(
        default=None,
        description="actions executed per inference: a number, 'chunk' (the whole chunk the "
        "backbone returns: a lerobot checkpoint's n_action_steps), or None: the env "
        "protocol's rule (LIBERO openpi 5, lerobot 'chunk'), else a lerobot checkpoint's "
        f"n_action_steps (as the idr policy executes), else {DEFAULT_REPLAN_STEPS}",
    )
    batched: bool | None = Field(default=None, description="one 3B forward (None: if it can)")

    @field_validator("replan_steps")
    @classmethod
    def _replan_positive(cls, v: int | str | None) -> int | str | None:
        if isinstance(v, int) and v < 1:
            raise ValueError(f"must be >= 1, 'chunk' or null (got {v})")
        return v


class EnvConfig(StrictModel):
    suite: str = Field(description="env suite, e.g. fake_marker, tabletop, libero_spatial")
    tasks: list[str] | None = Field(default=None, description="task ids; None = all of the suite")
    params: dict[str, Any] = Field(default_factory=dict)
    python: str | None = Field(
        default=None,
        min_length=1,
        description="interpreter of an env server: the simulator runs in a child process of "
        "each actor started from it (another venv, e.g. .venv-calvin/bin/python for PyBullet on "
        "Python 3.11); None: in the actor's own process. Results are the same either way",
    )
    server_timeout_s: float = Field(
        default=120.0,
        gt=0,
        description="env server: a start or a request taking longer is killed (an actor-level "
        "fault: the server is restarted and the episode run again)",
    )
    perturbations: list[Any] = Field(
        default_factory=lambda: ["none"],
        description="every task crossed with these: none (the task as it is) or KIND:SEVERITY "
        "(or {kind, severity}), e.g. [none, camera_shift:0.12, image_noise:0.3]; a task of "
        "env.tasks may name its own: pick_color@light_dim:0.4",
    )

    @field_validator("perturbations")
    @classmethod
    def _perturbations(cls, values: list[Any]) -> list[str]:
        from workers.envs.wrappers.perturbation_grammar import parse

        if not values:
            raise ValueError("give at least one (none: the tasks as they are)")
        out = []
        for v in values:
            p = parse(v)
            out.append("none" if p is None else p.text)
        if len(set(out)) != len(out):
            raise ValueError(f"{out} lists a perturbation twice")
        return out


class InterventionSettings(StrictModel):
    """do(V) and do(S) (``idr_core.interventions``): ``state_space: centered`` (the default)
    takes do(S) about the base's dataset mean state in physical units, the same counterfactual
    for every normalizer."""

    strategy: Literal["zero", "mean", "gaussian"] = "zero"
    image_space: Literal["raw", "normalized"] = "raw"
    state_space: Literal["raw", "centered", "normalized"] = "centered"
    noise_scale: float = Field(default=0.5, ge=0)


class TrackingConfig(StrictModel):
    enabled: bool = True
    uri: str | None = Field(
        default=None, description="MLflow URI; None = sqlite in the output root"
    )
    experiment: str = "idr-eval"
    reconnect_wait_s: float = Field(
        default=60.0,
        ge=0,
        description="a tracking server that goes down mid-run: at the end of the run, wait this "
        "long for it to come back before leaving MLflow to a rerun (the Parquet files are "
        "written either way)",
    )


class VideoConfig(StrictModel):
    episodes: int = Field(
        default=0,
        ge=0,
        description="the first N episodes of each task and cell as MP4 (RUN_DIR/videos/, and "
        "MLflow artifacts of the cell's run); 0: none (each recorded step renders its camera)",
    )
    camera: str | None = Field(default=None, description="the env camera; None: its first")
    fps: float | None = Field(default=None, gt=0, description="None: the env's control rate")


MIN_HELD_OUT = 10  # held-out calibration episodes per task, at least


class CalibrationConfig(StrictModel):
    """Held-out tau calibration: the diagnose cell runs on episodes of their own (indices
    disjoint from the evaluated ones, the run's seed), and only those fit tau. Controls (tasks
    under ``image_blackout``, and the tasks or cells named in ``controls``) never enter the fit.
    Without this block a run fits tau on its evaluated episodes (the paper's rule as it was)."""

    episodes_per_task: int = Field(
        default=MIN_HELD_OUT,
        description=f"held-out episodes per calibration task (at least {MIN_HELD_OUT})",
    )
    first_episode: int | None = Field(
        default=None,
        ge=0,
        description="index of the first held-out episode (they run first_episode ... "
        "first_episode + episodes_per_task - 1 under the run's seed); None: right after the "
        "evaluated ones (episodes_per_task of the run)",
    )
    tasks: list[str] | None = Field(
        default=None,
        description="the task ids whose held-out episodes fit tau (a subset of the run's "
        "tasks, no control); None: every task of the run that is not a control",
    )
    controls: list[str] = Field(
        default_factory=list,
        description="task ids or cell ids kept out of the fit, besides every task under "
        "image_blackout (the image-zeroed control), which is one always",
    )

    @field_validator("episodes_per_task")
    @classmethod
    def _enough(cls, v: int) -> int:
        if v < MIN_HELD_OUT:
            raise ValueError(
                f"{v} held-out episodes per task fit tau on too few; give at least "
                f"{MIN_HELD_OUT} (calibration.episodes_per_task={MIN_HELD_OUT})"
            )
        return v

    def first(self, evaluated: int) -> int:
        """The first held-out episode index of a run of ``evaluated`` episodes per task."""
        return evaluated if self.first_episode is None else self.first_episode

    def indices(self, evaluated: int) -> range:
        first = self.first(evaluated)
        return range(first, first + self.episodes_per_task)


class RunConfig(StrictModel):
    name: str = Field(
        default="run", description="run name; the default RUN_DIR is <output_root>/<name>"
    )
    backbone: BackboneConfig
    env: EnvConfig
    episodes_per_task: int = Field(default=1, ge=1)
    seed: int = Field(default=0, ge=0, le=2**63 - 1)  # stored as int64
    idr: RefinerSettings = Field(
        default_factory=RefinerSettings,
        description="IDR parameters shared by all cells (alpha, beta, ...); a grid axis "
        "overrides one per cell",
    )
    intervention: InterventionSettings = InterventionSettings()
    grid: list[dict[str, Any]] = Field(
        default_factory=lambda: [{"mode": ["baseline", "E"]}],
        description="groups of parameter lists: zipped within a group, crossed across groups",
    )
    executor: ExecutorConfig = InActorExecutor()
    tracking: TrackingConfig = TrackingConfig()
    videos: VideoConfig = VideoConfig()
    calibration: CalibrationConfig | None = Field(
        default=None,
        description="held-out tau calibration (CalibrationConfig); None: tau: calibrated is "
        "fitted on the evaluated episodes of the diagnose cell",
    )
    output_root: str = "runs"
    max_cells: int = Field(
        default=16,
        ge=1,
        description="a grid with more cells is refused unless confirmed (`idr-eval run --yes`)",
    )
    max_episodes: int = Field(
        default=100_000,
        ge=1,
        description="a plan of more episodes (cells x tasks x episodes_per_task) is refused "
        "before it is built, unless confirmed (`idr-eval run --yes`)",
    )

    @field_validator("name")
    @classmethod
    def _name_is_one_path_component(cls, v: str) -> str:
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}", v):
            raise ValueError(
                f"{v!r} must be one path component (letters, digits, '.', '_', '-'; no '/' or "
                "'..'): the default RUN_DIR is <output_root>/<name>"
            )
        return v

    @field_serializer("idr")
    def _idr_as_given(self, v: RefinerSettings) -> dict[str, Any]:
        # what the config gives, as run.json and the fingerprint have always held it
        return v.given()

    @model_validator(mode="after")
    def _cells_valid(self) -> RunConfig:
        cells = self.cells()  # raises ValueError naming the bad grid entry
        calibrated = [c for c in cells if c.calibrated_tau is not None]
        if calibrated and not any(c.idr.mode == "diagnose" for c in cells):
            raise ValueError(
                "tau: calibrated needs a diagnose cell in the grid to measure E_img on "
                "(add mode diagnose, e.g. grid=[{mode: [diagnose, E]}])"
            )
        for c in calibrated:
            if c.calibration_source(cells) is None:
                iv = ", ".join(f"{k}={v}" for k, v in c.params().items() if k in INTERVENTION_KEYS)
                raise ValueError(
                    f"cell {c.cell_id!r} has tau: {c.calibrated_tau.text} but no diagnose cell "
                    f"measures its intervention ({iv}, eps={c.idr.eps:g}); the effects depend on "
                    "it: put mode diagnose in a group crossed with the intervention parameters, "
                    "e.g. grid=[{mode: [diagnose, E]}, {strategy: [zero, mean]}]"
                )
        if self.calibration is not None:
            from pipeline.planning.calibration_block import check_block

            check_block(self, cells)
        return self

    def cells(self) -> list[Cell]:
        return expand_grid(self.grid, base={**self.idr.given(), **self.intervention.model_dump()})

    def fingerprint(self) -> str:
        """Hash of what determines results; a run dir may be resumed only with the same one."""
        keep = self.model_dump(
            exclude={
                "executor": True,
                "tracking": True,
                "videos": True,  # what is recorded, not what happens
                "output_root": True,
                "name": True,
                "max_cells": True,
                "max_episodes": True,
                # where the simulator runs does not change results (in-process or env server)
                "env": {"python", "server_timeout_s"},
            }
        )
        if keep["env"].get("perturbations") == ["none"]:  # the default: as before it existed
            del keep["env"]["perturbations"]
        if keep.get("calibration") is None:  # the default: as before it existed
            keep.pop("calibration", None)
        return hashlib.sha256(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()[
            :16
        ]


ALLOWED_VALUES = {"mode": MODES, "guidance": GUIDANCES, "strategy": STRATEGIES, "space": SPACES}


def _model_at(loc: tuple[Any, ...]) -> tuple[list[str], type[BaseModel] | None]:
    """``loc`` as the user writes the key, and the model whose fields its last part names (None:
    not a model). Pydantic puts a discriminated union's tag in ``loc`` (``executor.shared.
    max_batch``): dropped, its variant taken."""
    parts: list[str] = []
    model: type[BaseModel] | None = RunConfig
    variants: dict[str, type[BaseModel]] = {}
    for part in loc:
        if str(part) in variants:
            model, variants = variants[str(part)], {}
            continue
        parts.append(str(part))
        field = model.model_fields.get(str(part)) if model is not None else None
        model, variants = None, {}
        ann = getattr(field, "annotation", None)
        if isinstance(ann, type) and issubclass(ann, BaseModel):
            model = ann
        elif field is not None and isinstance(field.discriminator, str):
            for cls in typing.get_args(ann):
                tags = typing.get_args(cls.model_fields[field.discriminator].annotation)
                variants.update(dict.fromkeys(tags, cls))
    return parts, model


QUOTE = "'"


def _format_errors(err: ValidationError, source: str) -> str:
    lines = []
    for e in err.errors():
        parts, _ = _model_at(e["loc"])
        loc = ".".join(parts) or "<root>"
        msg = e["msg"].removeprefix("Value error, ")
        if e["type"] == "extra_forbidden":
            _, parent = _model_at(e["loc"][:-1])
            known = list(parent.model_fields) if parent else []
            close = difflib.get_close_matches(str(e["loc"][-1]), known, n=1)
            hint = (
                f"; did you mean {close[0]!r}?"
                if close
                else (f"; known keys: {known}" if known else "")
            )
            msg = f"unknown key{hint}"
        elif e["type"] == "missing":
            msg = "required field is missing"
        elif e["type"] == "union_tag_invalid":  # e.g. executor.policy=sharded
            ctx = e["ctx"]
            loc = f"{loc}.{ctx['discriminator'].strip(QUOTE)}"
            msg = f"Input should be one of {ctx['expected_tags']} (got {ctx['tag']!r})"
        elif "input" in e and e["type"] not in ("value_error",):
            msg = f"{msg} (got {e['input']!r})"
        # a message naming its own key (executor.max_batch applies to ...) stands alone
        lines.append(f"  {msg}" if msg.startswith(f"{loc}.") else f"  {loc}: {msg}")
    return f"invalid config {source}:\n" + "\n".join(lines)


def load_config(path: str | Path, overrides: list[str] | None = None) -> RunConfig:
    """Read a YAML config, apply dotted overrides, validate. Raises ConfigError."""
    path = Path(path)
    if not path.is_file():
        presets = (
            sorted(p.name for p in Path("conf").glob("*.yaml")) if Path("conf").is_dir() else []
        )
        close = difflib.get_close_matches(path.name, presets, n=1)
        hint = (
            f"; did you mean conf/{close[0]}?"
            if close
            else (f"; presets: {presets}" if presets else "")
        )
        raise ConfigError(f"config file {str(path)!r} not found{hint}")
    try:
        data = safe_load_yaml(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ConfigError(f"config {path} is not valid YAML: {e}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config {path} must be a mapping of keys, got {type(data).__name__}")
    return config_from_dict(apply_overrides(data, overrides or []), source=str(path))


def config_from_dict(data: dict[str, Any], source: str = "<dict>") -> RunConfig:
    try:
        return RunConfig.model_validate(data)
    except ValidationError as e:
        raise ConfigError(_format_errors(e, source)) from None


def load_run_record(path: str | Path) -> RunConfig:
    """A run dir's ``config.yaml`` read as the record of what its run ran: keys that had no
    effect on the run (``executor_config.without_ignored_keys``) are dropped before it is
    validated. A config given to run is checked whole (:func:`load_config`). Raises
    ConfigError."""
    path = Path(path)
    try:
        data = safe_load_yaml(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as e:
        raise ConfigError(f"run record {path} cannot be read: {e}") from None
    if isinstance(data, dict) and isinstance(data.get("executor"), dict):
        data = {**data, "executor": without_ignored_keys(data["executor"])}
    return config_from_dict(data, source=str(path))


def dump_config(cfg: RunConfig) -> str:
    return yaml.dump(cfg.model_dump(mode="json"), Dumper=NoAliasDumper, sort_keys=False)
