"""A study: several runs (architecture x environment), each an ordinary config plus overrides,
run one after another into ``OUT/<arch>@<env>`` and reported together.

The paper's observations compare backbones across environments, and a run holds one backbone,
so the comparison is a set of runs. A study file lists them::

    name: paper_observations
    set: [episodes_per_task=10]            # overrides applied to every run (optional)
    runs:
      - {arch: tiny_vla, env: tabletop, config: conf/zoo/tabletop.yaml,
         set: [backbone.params.path=checkpoints/zoo/tiny_vla]}

Every run's config is loaded and checked (keys, values, overrides) before the first episode of
any run, so an error in the last entry costs nothing.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from pipeline.planning.config import ConfigError, RunConfig, load_config

STUDY_KEYS = {"name", "set", "runs"}
RUN_KEYS = {"arch", "env", "config", "set"}


@dataclass(frozen=True)
class StudyRun:
    """One run of a study: which architecture in which environment, from which config."""

    arch: str
    env: str
    config_path: Path
    overrides: tuple[str, ...]
    config: RunConfig

    @property
    def label(self) -> str:
        return f"{self.arch}@{self.env}"


@dataclass(frozen=True)
class Study:
    name: str
    runs: tuple[StudyRun, ...]


def _overrides(value: Any, where: str) -> tuple[str, ...]:
    if value is None:
        return ()
    if not isinstance(value, list) or not all(isinstance(v, str) and "=" in v for v in value):
        raise ConfigError(
            f"{where}: write a list of dotted key=value overrides, as on the command line, "
            "e.g. set: [episodes_per_task=10]"
        )
    return tuple(value)


def _refuse_unknown(
    mapping: dict, allowed: frozenset[str] | set[str], where: str, what: str
) -> None:
    unknown = set(mapping) - set(allowed)
    if unknown:
        raise ConfigError(f"{where}: unknown keys {sorted(unknown)}; {what} has {sorted(allowed)}")


def load_study(
    path: str | Path, extra: list[str] | None = None, only: list[str] | None = None
) -> Study:
    """Read and check a study file; ``extra``: overrides given on the command line (after the
    file's own, so they win); ``only``: the labels (``arch@env``) of the runs to keep, e.g. those
    whose checkpoints this machine holds (the others' configs are not loaded)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"study file {path} does not exist")
    raw = yaml.safe_load(path.read_text()) or {}
    if not isinstance(raw, dict) or "runs" not in raw:
        raise ConfigError(
            f"{path}: a study file has a `runs:` list (see pipeline/planning/study.py)"
        )
    _refuse_unknown(raw, STUDY_KEYS, f"{path}", "a study")
    shared = _overrides(raw.get("set"), f"{path}: set")
    runs: list[StudyRun] = []
    if not isinstance(raw["runs"], list) or not raw["runs"]:
        raise ConfigError(f"{path}: runs must be a non-empty list of {{arch, env, config, set}}")
    entries: list[tuple[str, str, dict]] = []
    for i, entry in enumerate(raw["runs"]):
        where = f"{path}: runs[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: write a mapping {{arch, env, config, set}}")
        missing = {"arch", "env", "config"} - set(entry)
        if missing:
            raise ConfigError(
                f"{where}: missing {sorted(missing)} (each run names arch, env, config)"
            )
        _refuse_unknown(entry, RUN_KEYS, where, "a run")
        entries.append((where, f"{entry['arch']}@{entry['env']}", entry))
    if only is not None:
        labels = [label for _, label, _ in entries]
        unknown = sorted(set(only) - set(labels))
        if unknown or not only:
            raise ConfigError(
                f"--only {','.join(only)}: {unknown or 'no run'} not in {path}; "
                f"its runs are {', '.join(labels)}"
            )
        entries = [e for e in entries if e[1] in only]
    for where, label, entry in entries:
        own = _overrides(entry.get("set"), f"{where}.set")
        overrides = (*shared, *own, *(extra or []))
        try:
            cfg = load_config(entry["config"], list(overrides))
        except ConfigError as e:
            raise ConfigError(f"{where} ({label}): {e}") from None
        runs.append(
            StudyRun(str(entry["arch"]), str(entry["env"]), Path(entry["config"]), overrides, cfg)
        )
    labels = [r.label for r in runs]
    dupes = sorted({lab for lab in labels if labels.count(lab) > 1})
    if dupes:
        raise ConfigError(f"{path}: runs {dupes} appear twice; each (arch, env) once")
    return Study(str(raw.get("name") or path.stem), tuple(runs))
