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

Training seeds. A member (``arch@env``) trained several times lists one run per training seed,
each with its ``seed`` and its checkpoint::

      - {arch: smolvla, env: metaworld, seed: 0, config: conf/zoo/metaworld.yaml,
         set: [backbone.params.path=checkpoints/zoo/metaworld/smolvla]}
      - {arch: smolvla, env: metaworld, seed: 1, config: conf/zoo/metaworld.yaml,
         set: [backbone.params.path=checkpoints/zoo/metaworld/smolvla_seed1]}

Such a run's label is ``arch@env:seedN`` (its run dir, its name for ``--only``); the member's
figures are pooled over its seeds with a two-level bootstrap (pipeline.results.seeds), and an
endpoint naming the member (``arch@env``) is tested on the pooled difference. Either every run
of a member names its seed or none does.

Declared endpoints. A study states its primary comparisons before its data::

    endpoints:
      primary:
        - {member: smolvla@metaworld, compare: [E, diagnose]}   # success of E - diagnose
        - {member: tiny_vla@tabletop, compare: [E, diagnose], suite: tabletop}

``member`` is a member's ``arch@env`` (pooled over its training seeds) or one seed's run
``arch@env:seedN``, ``compare: [CELL, REFERENCE]`` two of its cells (paired by
episode, McNemar), ``suite`` (optional) restricts the pairs to one suite's episodes. Their hash
is written to ``OUT/endpoints.json`` before the first episode (:func:`pin_endpoints`); changing
them once the study holds episodes is refused. The report gives them with Holm's correction and
labels every other comparison exploratory. A run with ``tau: calibrated`` needs a
``calibration:`` block (held-out episodes fit tau: pipeline.results.calibration).
"""

from __future__ import annotations

import difflib
import hashlib
import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import yaml

from pipeline.planning.config import ConfigError, RunConfig, load_config

if TYPE_CHECKING:
    from pipeline.planning.plan import RunPlan

STUDY_KEYS = {"name", "set", "runs", "endpoints"}
RUN_KEYS = {"arch", "env", "config", "set", "seed"}
ENDPOINT_KEYS = {"member", "compare", "suite"}
ENDPOINTS_FILE = "endpoints.json"  # OUT/endpoints.json: the declared endpoints and their hash
ENDPOINTS_SYNTAX = (
    "write endpoints: {primary: [{member: ARCH@ENV, compare: [CELL, REFERENCE_CELL]}, ...]} "
    "(optional suite: SUITE per endpoint)"
)


@dataclass(frozen=True)
class Endpoint:
    """One declared primary comparison: success of ``cell`` minus ``reference`` in ``member``'s
    run, paired by episode (restricted to ``suite`` when given)."""

    member: str
    cell: str
    reference: str
    suite: str | None = None

    @property
    def label(self) -> str:
        where = f" [{self.suite}]" if self.suite else ""
        return f"{self.member}: {self.cell} vs {self.reference}{where}"


@dataclass(frozen=True)
class StudyRun:
    """One run of a study: which architecture in which environment, from which config."""

    arch: str
    env: str
    config_path: Path
    overrides: tuple[str, ...]
    config: RunConfig
    seed: int | None = None  # the training seed of its checkpoint, where the member lists seeds

    @property
    def member(self) -> str:
        """The architecture in its environment, whichever training seed."""
        return f"{self.arch}@{self.env}"

    @property
    def label(self) -> str:
        """The run's own name (its run dir): the member, and its training seed if listed."""
        return run_label(self.arch, self.env, self.seed)


def run_label(arch: str, env: str, seed: int | None) -> str:
    return f"{arch}@{env}" if seed is None else f"{arch}@{env}:seed{seed}"


@dataclass(frozen=True)
class Study:
    name: str
    runs: tuple[StudyRun, ...]
    endpoints: tuple[Endpoint, ...] = ()
    path: Path = Path("study.yaml")

    def endpoints_hash(self) -> str:
        return endpoints_hash(self.endpoints)

    def runs_of(self, name: str) -> list[StudyRun]:
        """The runs an endpoint's ``member`` names: one run, or every seed of a member."""
        return [r for r in self.runs if name in (r.label, r.member)]


def endpoints_hash(endpoints: Sequence[Endpoint]) -> str:
    """sha256 of the declared endpoints, in their declared order (a reorder is a change: it
    is how the report lists them)."""
    text = json.dumps([asdict(e) for e in endpoints], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def _endpoints(value: Any, path: Path, labels: list[str]) -> tuple[Endpoint, ...]:
    """The ``endpoints:`` block, its members checked against the study's runs."""
    if value is None:
        return ()
    if not isinstance(value, dict) or set(value) != {"primary"}:
        raise ConfigError(f"{path}: endpoints: {ENDPOINTS_SYNTAX}")
    entries = value["primary"]
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{path}: endpoints.primary: a non-empty list; {ENDPOINTS_SYNTAX}")
    out: list[Endpoint] = []
    for i, e in enumerate(entries):
        where = f"{path}: endpoints.primary[{i}]"
        if not isinstance(e, dict) or not {"member", "compare"} <= set(e):
            raise ConfigError(f"{where}: {ENDPOINTS_SYNTAX}")
        _refuse_unknown(e, ENDPOINT_KEYS, where, "an endpoint")
        member, compare, suite = e["member"], e["compare"], e.get("suite")
        if member not in labels:
            close = difflib.get_close_matches(str(member), labels, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ConfigError(
                f"{where}.member: {member!r} is not a member or run of this study; {hint}they "
                f"are {', '.join(labels)} (ARCH@ENV, or ARCH@ENV:seedN for one training seed)"
            )
        if (
            not isinstance(compare, list)
            or len(compare) != 2
            or not all(isinstance(c, str) for c in compare)
            or compare[0] == compare[1]
        ):
            raise ConfigError(
                f"{where}.compare: two different cells of {member}, [CELL, REFERENCE], "
                f"e.g. [E, diagnose] (got {compare!r})"
            )
        if suite is not None and not isinstance(suite, str):
            raise ConfigError(f"{where}.suite: a suite name, e.g. tabletop (got {suite!r})")
        out.append(Endpoint(str(member), compare[0], compare[1], suite))
    dupes = sorted({e.label for e in out if out.count(e) > 1})
    if dupes:
        raise ConfigError(f"{path}: endpoints.primary: {dupes} declared twice; each once")
    return tuple(out)


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
    raw = _read_study_file(path)
    shared = _overrides(raw.get("set"), f"{path}: set")
    entries = _run_entries(path, raw["runs"])
    _check_seeds(path, [e for _, _, e in entries])
    members = sorted({f"{e['arch']}@{e['env']}" for _, _, e in entries})
    all_labels = [label for _, label, _ in entries]
    if only is not None:
        entries = _only(path, entries, only)
    runs = [_load_run(where, label, entry, shared, extra) for where, label, entry in entries]
    labels = [r.label for r in runs]
    dupes = sorted({lab for lab in labels if labels.count(lab) > 1})
    if dupes:
        raise ConfigError(
            f"{path}: runs {dupes} appear twice; each (arch, env) once, or once per training seed"
        )
    endpoints = _endpoints(
        raw.get("endpoints"), path, [*all_labels, *(m for m in members if m not in all_labels)]
    )
    study = Study(str(raw.get("name") or path.stem), tuple(runs), endpoints, path)
    _check_endpoint_cells(path, study)
    return study


def _read_study_file(path: Path) -> dict:
    """The study file's top-level mapping, with a ``runs:`` key and no unknown keys."""
    if not path.is_file():
        raise ConfigError(f"study file {path} does not exist")
    raw = yaml.safe_load(path.read_text()) or {}
    if not isinstance(raw, dict) or "runs" not in raw:
        raise ConfigError(
            f"{path}: a study file has a `runs:` list (see pipeline/planning/study.py)"
        )
    _refuse_unknown(raw, STUDY_KEYS, f"{path}", "a study")
    return raw


def _run_entries(path: Path, raw_runs: Any) -> list[tuple[str, str, dict]]:
    """Each entry of ``runs:`` checked, as (where it is in the file, its label, the entry)."""
    if not isinstance(raw_runs, list) or not raw_runs:
        raise ConfigError(f"{path}: runs must be a non-empty list of {{arch, env, config, set}}")
    entries: list[tuple[str, str, dict]] = []
    for i, entry in enumerate(raw_runs):
        where = f"{path}: runs[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(f"{where}: write a mapping {{arch, env, config, set}}")
        missing = {"arch", "env", "config"} - set(entry)
        if missing:
            raise ConfigError(
                f"{where}: missing {sorted(missing)} (each run names arch, env, config)"
            )
        _refuse_unknown(entry, RUN_KEYS, where, "a run")
        seed = entry.get("seed")
        if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or seed < 0):
            raise ConfigError(
                f"{where}.seed: the training seed of the run's checkpoint, an integer >= 0 "
                f"(got {seed!r})"
            )
        entries.append((where, run_label(entry["arch"], entry["env"], seed), entry))
    return entries


def _only(
    path: Path, entries: list[tuple[str, str, dict]], only: list[str]
) -> list[tuple[str, str, dict]]:
    """The entries ``--only`` names (each of its labels must be one of the study's runs)."""
    labels = [label for _, label, _ in entries]
    unknown = sorted(set(only) - set(labels))
    if unknown or not only:
        raise ConfigError(
            f"--only {','.join(only)}: {unknown or 'no run'} not in {path}; "
            f"its runs are {', '.join(labels)}"
        )
    return [e for e in entries if e[1] in only]


def _load_run(
    where: str, label: str, entry: dict, shared: tuple[str, ...], extra: list[str] | None
) -> StudyRun:
    """A run with its config loaded under the study's overrides, the run's own, then the
    command line's (the last wins)."""
    own = _overrides(entry.get("set"), f"{where}.set")
    overrides = (*shared, *own, *(extra or []))
    try:
        cfg = load_config(entry["config"], list(overrides))
    except ConfigError as e:
        raise ConfigError(f"{where} ({label}): {e}") from None
    return StudyRun(
        str(entry["arch"]),
        str(entry["env"]),
        Path(entry["config"]),
        overrides,
        cfg,
        entry.get("seed"),
    )


def _check_endpoint_cells(path: Path, study: Study) -> None:
    """Each primary endpoint's two cells are cells of every loaded run of its member (a run
    left out by ``--only`` is not loaded, so not checked)."""
    for i, e in enumerate(study.endpoints):
        for run in study.runs_of(e.member):
            cells = [c.cell_id for c in run.config.cells()]
            for name in (e.cell, e.reference):
                if name not in cells:
                    raise ConfigError(
                        f"{path}: endpoints.primary[{i}].compare: {run.label} has no cell "
                        f"{name!r}; its cells are {cells}"
                    )


def _check_seeds(path: Path, entries: list[dict]) -> None:
    """Either every run of a member names its training seed or none does (a seedless run
    beside seeded ones would be pooled as a seed of unknown origin)."""
    by_member: dict[str, list[Any]] = {}
    for e in entries:
        by_member.setdefault(f"{e['arch']}@{e['env']}", []).append(e.get("seed"))
    for member, seeds in by_member.items():
        if None in seeds and any(x is not None for x in seeds):
            raise ConfigError(
                f"{path}: runs of {member}: {seeds.count(None)} without a seed beside seeds "
                f"{sorted(s for s in seeds if s is not None)}; give every run of {member} its "
                "training seed (seed: N)"
            )


def check_study_plans(study: Study, plans: Sequence[RunPlan]) -> None:
    """What needs each run's plan (its tasks), checked before any episode of any run: a run
    that calibrates tau has a held-out ``calibration:`` block, and an endpoint's suite is one
    of its member's. Raises ConfigError naming the field and the fix."""
    for run, plan in zip(study.runs, plans, strict=True):
        if plan.cfg.calibration is None and any(c.calibrated_tau for c in plan.cfg.cells()):
            raise ConfigError(
                f"{study.path}: {run.label}: calibration: a study fits tau on held-out episodes; "
                f"add a calibration: block to {run.config_path} or to the study's set: "
                '["calibration={episodes_per_task: 10}"] (docs/configuration.md)'
            )
    suites = {
        run.label: sorted({str(t.suite) for t in plan.tasks})
        for run, plan in zip(study.runs, plans, strict=True)
    }
    for i, e in enumerate(study.endpoints):
        for run in study.runs_of(e.member) if e.suite is not None else ():
            if e.suite not in suites[run.label]:
                raise ConfigError(
                    f"{study.path}: endpoints.primary[{i}].suite: {run.label} has no suite "
                    f"{e.suite!r}; its suites are {suites[run.label]} (or leave suite out: all)"
                )


def study_holds_episodes(out: Path) -> bool:
    """Whether any run dir of the study under ``out`` has a stored episode (held-out ones
    included)."""
    return any(out.glob("*/episodes/cell=*/*.parquet")) or any(
        out.glob("*/calibration_episodes/episodes/cell=*/*.parquet")
    )


def pin_endpoints(study: Study, out: Path) -> Path:
    """Write ``OUT/endpoints.json`` (the declared endpoints and their hash) before the first
    episode; refuse a study whose endpoints differ from the pinned ones once it holds episodes
    (ConfigError naming the study file and how to start a new study)."""
    target = out / ENDPOINTS_FILE
    current = study.endpoints_hash()
    if target.is_file():
        pinned = json.loads(target.read_text())
        if pinned.get("hash") == current:
            return target
        if study_holds_episodes(out):
            raise ConfigError(
                f"{study.path}: endpoints: the declared primary endpoints differ from those "
                f"pinned in {target} before this study's first episode (hash "
                f"{str(pinned.get('hash'))[:12]} -> {current[:12]}), and {out} holds episodes: "
                "endpoints are fixed before the data. Restore them in the study file, or start "
                f"a new study with a new --out (e.g. --out {out}-v2)"
            )
    from pipeline.rundir import write_text_atomic

    out.mkdir(parents=True, exist_ok=True)
    record = {
        "study_file": str(study.path),
        "hash": current,
        "primary": [asdict(e) for e in study.endpoints],
    }
    write_text_atomic(target, json.dumps(record, indent=2) + "\n")
    return target
