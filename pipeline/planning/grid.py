"""A run's grid: its cells, from parameter lists, and its episodes, cells x tasks x episodes.

Cells: parameter lists in groups, zipped within a group, crossed across.

Like robomimic's sweep generator: ``[{mode: [baseline, E]}, {alpha: [0.05, 0.1], tau: [5, 7]}]``
gives baseline plus E x {(0.05, 5), (0.1, 7)}. Cell ids are built from the varied parameters
with short names (``E_a0.05_tau5``), so runs read well in tables and in the MLflow UI. All
``baseline`` cells behave the same whatever the other parameters, so they collapse into one
cell named ``baseline``; ``diagnose`` cells collapse likewise over the parameters that change
neither what they execute nor what they measure (alpha, beta, lam, tau, guidance), keeping
the intervention settings (``diagnose_ivmean``): one diagnose cell per intervention is what tau
calibration needs.

``tau`` is a number (``999`` or ``.inf``: always on) or a calibrated form, resolved after the
diagnose cell ran, per backbone x suite (see :class:`TauSpec`): ``calibrated`` (the paper's
rule: the mean diagnosed effect), ``calibrated*K`` (K times that mean) or ``calibrated_qP``
(its P-th percentile), also combined (``calibrated_q90*0.5``).

Episodes: a plan of a paper-sized grid has hundreds of thousands of episodes; :class:`SpecGrid`
is a ``Sequence[EpisodeSpec]`` that makes the spec at an index when asked (the scheduler walks
it once, skipping stored keys), so a large run starts without building them all. Order: cell by
cell, task by task, episode by episode, as every cell sees the same tasks and episodes. A
cell's settings reach the episode here, with tau set per suite once calibrated
(:meth:`Cell.idr_for`): the one step between the config and the worker.
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass, field, fields
from typing import Any, overload

from idr_core.calibration import TauSpec, parse_tau
from idr_core.interventions import InterventionConfig
from idr_core.methods import SETTINGS, method_of, unread_settings
from idr_core.refiner import RefinerConfig

from workers.envs.base import TaskSpec
from workers.episode.rows import EpisodeSpec

IDR_KEYS = tuple(f.name for f in fields(RefinerConfig))
INTERVENTION_KEYS = tuple(f.name for f in fields(InterventionConfig) if f.name != "seed")
CELL_KEYS = frozenset(IDR_KEYS + INTERVENTION_KEYS)

#: Short names used in cell ids; the mode is written bare.
SHORT_NAMES = {
    "mode": "",
    "alpha": "a",
    "beta": "b",
    "lam": "lam",
    "tau": "tau",
    "eps": "eps",
    "guidance": "g",
    "strategy": "iv",
    "image_space": "isp",
    "state_space": "ssp",
    "noise_scale": "ns",
    "w": "w",
    "samples": "k",
    "te_coeff": "tec",
    "horizon": "h",
    "clip_actions": "clip",
}
#: modes that keep today's rule for IDR's settings on a grid axis (baseline and diagnose
#: collapse over them; E's ablations ignore what they drop): the other methods refuse a
#: setting they do not read, and every mode refuses the methods' own settings it ignores
_LENIENT_MODES = frozenset({"baseline", "diagnose", "A", "B", "C", "D", "E", "F"})
_METHOD_SETTINGS = frozenset({"w", "samples", "te_coeff", "horizon"})


#: Parameters a diagnose cell keeps in its id: those that change what it measures.
DIAGNOSE_KEYS = frozenset((*INTERVENTION_KEYS, "eps"))


@dataclass(frozen=True)
class Cell:
    """One IDR configuration of a grid."""

    cell_id: str
    idr: RefinerConfig
    intervention: InterventionConfig
    varied: tuple[tuple[str, Any], ...]  # the grid parameters that made this cell, in order
    # tau: calibrated[...] -> tau is set, after the diagnose cell ran, from the effect it
    # measured, per suite (the paper's rule); idr.tau holds a placeholder until then
    calibrated_tau: TauSpec | None = None
    # after calibration: tau per suite (None: idr.tau as it is)
    tau_by_suite: Mapping[str, float] | None = None

    def idr_for(self, suite: str | None) -> RefinerConfig:
        """The settings an episode on ``suite`` runs with: ``idr`` with tau set for the suite
        once calibrated."""
        if self.tau_by_suite is None:
            return self.idr
        return dataclasses.replace(self.idr, tau=float(self.tau_by_suite[suite or ""]))

    def params(self) -> dict[str, Any]:
        """Flat parameters, for tables and MLflow (a calibrated tau as its spelling)."""
        out = {**asdict(self.idr), **{k: getattr(self.intervention, k) for k in INTERVENTION_KEYS}}
        if self.calibrated_tau is not None:
            out["tau"] = self.calibrated_tau.text
        return out

    @property
    def role(self) -> str:
        """``baseline`` (backbone only), ``diagnose`` (measures, executes a_base), ``idr`` (a
        refining mode, A-F), ``control`` (E's controls: random, shuffled, scale_free) or
        ``method`` (another test-time method): what the cell is, for filters in tables and in
        the UI."""
        mode = self.idr.mode
        if mode in ("baseline", "diagnose"):
            return mode
        if mode in ("random", "shuffled", "scale_free"):
            return "control"
        return "idr" if mode in "ABCDEF" else "method"

    def meaningful_params(self) -> dict[str, Any]:
        """``params()`` less what the cell's mode does not use, so that a comparison never
        places a cell at a value it ignores: a baseline runs no counterfactual passes (no
        IDR or intervention parameter applies); a diagnose cell measures the effects (its
        intervention settings and eps apply) but never refines (alpha, beta, lam, tau and
        guidance do not); a refining mode uses all of them except what its ablation drops
        (D: no gate, so no tau; A: no stabilizer, so no beta or lam; B: no clip, so no
        lam). ``noise_scale`` only with the gaussian intervention."""
        params = self.params()
        reads = method_of(self.idr).reads
        keep = {"mode", *(k for k in params if k not in SETTINGS or k in reads)}
        if self.role == "baseline":
            keep = {"mode", *(reads & {"horizon"})}
        elif self.role == "diagnose":
            keep = {"mode", *DIAGNOSE_KEYS, *(reads & {"horizon"})}
        if self.idr.horizon is None:
            keep.discard("horizon")
        if not method_of(self.idr).diagnoses and self.role != "baseline":
            keep -= set(INTERVENTION_KEYS) - {"image_space"}  # no do(S) pass
            if "no_img" not in method_of(self.idr).passes:
                keep -= set(INTERVENTION_KEYS)
        if self.intervention.strategy != "gaussian":
            keep.discard("noise_scale")  # the std of the gaussian intervention only
        return {k: v for k, v in params.items() if k in keep}

    def calibration_source(self, cells: list[Cell]) -> Cell | None:
        """The diagnose cell whose measurements calibrate this cell's tau: the one with the
        same intervention settings and eps (the effects depend on them); None if there is none."""
        for c in cells:
            if (
                c.idr.mode == "diagnose"
                and c.intervention == self.intervention
                and c.idr.eps == self.idr.eps
            ):
                return c
        return None


def _fmt(value: Any) -> str:
    if isinstance(value, TauSpec):
        return value.short
    if isinstance(value, float):
        return "inf" if value == float("inf") else f"{value:g}"
    return str(value)


def cell_name(varied: list[tuple[str, Any]]) -> str:
    parts = [f"{SHORT_NAMES.get(k, k)}{_fmt(v)}" for k, v in varied]
    return "_".join(parts) or "default"


def _group_rows(i: int, group: Any) -> list[list[tuple[str, Any]]]:
    if not isinstance(group, dict) or not group:
        raise ValueError(f"grid[{i}] must be a non-empty mapping of parameter -> list of values")
    lists: dict[str, list[Any]] = {}
    for key, values in group.items():
        if key not in CELL_KEYS:
            raise ValueError(f"grid[{i}]: unknown parameter {key!r}; allowed: {sorted(CELL_KEYS)}")
        lists[key] = list(values) if isinstance(values, list | tuple) else [values]
        if key == "tau":
            try:
                lists[key] = [parse_tau(v) for v in lists[key]]
            except ValueError as e:
                raise ValueError(f"grid[{i}]: {e}") from None
    lengths = {k: len(v) for k, v in lists.items()}
    if len(set(lengths.values())) != 1:
        raise ValueError(
            f"grid[{i}]: lists in one group are zipped and must have equal lengths, got {lengths}"
        )
    n = next(iter(lengths.values()))
    if n == 0:
        raise ValueError(f"grid[{i}]: empty value list")
    return [[(k, lists[k][j]) for k in lists] for j in range(n)]


def expand_grid(groups: list[dict[str, Any]], base: dict[str, Any] | None = None) -> list[Cell]:
    """Cells of the grid, in a stable order; raises ValueError naming the bad entry."""
    base = dict(base or {})
    if "tau" in base:
        try:
            base["tau"] = parse_tau(base["tau"])
        except ValueError as e:
            raise ValueError(f"idr.{e}") from None
    unknown = set(base) - CELL_KEYS
    if unknown:
        raise ValueError(f"unknown IDR parameters {sorted(unknown)}; allowed: {sorted(CELL_KEYS)}")
    per_group = [_group_rows(i, g) for i, g in enumerate(groups)] or [[]]
    first_seen: dict[str, int] = {}
    for i, g in enumerate(groups):
        for key in g:
            if key in first_seen:
                raise ValueError(
                    f"grid: parameter {key!r} appears in groups {first_seen[key]} and {i}"
                )
            first_seen[key] = i
    cells: dict[str, Cell] = {}
    for combo in itertools.product(*per_group):
        varied = [kv for row in combo for kv in row]
        params = {**base, **dict(varied)}
        tau_spec = params.get("tau") if isinstance(params.get("tau"), TauSpec) else None
        if tau_spec is not None:
            params["tau"] = 0.0  # placeholder until calibration
        try:
            idr = RefinerConfig(**{k: params[k] for k in IDR_KEYS if k in params})
            iv = InterventionConfig(**{k: params[k] for k in INTERVENTION_KEYS if k in params})
        except (TypeError, ValueError) as e:
            raise ValueError(f"grid cell {dict(varied)}: {e}") from None
        given = [k for k, _ in varied]
        unread = [
            k
            for k in unread_settings(idr, given)
            if idr.mode not in _LENIENT_MODES or k in _METHOD_SETTINGS
        ]
        if unread:
            m = method_of(idr)
            raise ValueError(
                f"grid cell {dict(varied)}: mode {idr.mode!r} does not read {unread} (it reads "
                f"{sorted(m.reads) or 'no setting'}); put those values in a group of their own "
                "with the modes that read them (idr_core.methods)"
            )
        collapsed = idr.mode in ("baseline", "diagnose")
        horizon = [kv for kv in varied if kv[0] == "horizon"]
        if idr.mode == "baseline":
            varied = [("mode", "baseline"), *horizon]
            cid = cell_name(varied) if horizon else "baseline"
        elif idr.mode == "diagnose":
            varied = [("mode", "diagnose")] + [
                kv for kv in varied if kv[0] in DIAGNOSE_KEYS or kv[0] == "horizon"
            ]
            cid = cell_name(varied)
        else:
            cid = cell_name(varied)
        if cid in cells:
            if collapsed:
                continue
            raise ValueError(f"grid gives two cells named {cid!r}: a value is listed twice")
        # E's gated modes (D included, as before: its tau is recorded though unused)
        cells[cid] = Cell(
            cid, idr, iv, tuple(varied), calibrated_tau=tau_spec if idr.gated else None
        )
    return list(cells.values())


@dataclass(frozen=True)
class SpecGrid(Sequence[EpisodeSpec]):
    run_id: str
    cells: tuple[Cell, ...]
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
        return EpisodeSpec(
            run_id=self.run_id,
            cell_id=cell.cell_id,
            idr=cell.idr_for(task.suite),
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
