"""IDR cells from a grid: parameter lists in groups, zipped within a group, crossed across.

Like robomimic's sweep generator: ``[{mode: [baseline, E]}, {alpha: [0.05, 0.1], tau: [5, 7]}]``
gives baseline plus E x {(0.05, 5), (0.1, 7)}. Cell ids are built from the varied parameters
with short names (``E_a0.05_tau5``), so runs read well in tables and in the MLflow UI. All
``baseline`` cells behave the same whatever the other parameters, so they collapse into one
cell named ``baseline``.
"""

from __future__ import annotations

import itertools
from dataclasses import asdict, dataclass, fields, replace
from typing import Any

from workers.idr import IDRConfig
from workers.interventions import InterventionConfig

IDR_KEYS = tuple(f.name for f in fields(IDRConfig))
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
}


CALIBRATED = "calibrated"


@dataclass(frozen=True)
class Cell:
    """One IDR configuration of a grid."""

    cell_id: str
    idr: IDRConfig
    intervention: InterventionConfig
    varied: tuple[tuple[str, Any], ...]  # the grid parameters that made this cell, in order
    # tau: calibrated -> tau is set, after the diagnose cell ran, to the mean E_img it measured
    # (the paper's rule); idr.tau holds a placeholder until then
    calibrated_tau: bool = False

    def with_tau(self, tau: float) -> Cell:
        return replace(self, idr=replace(self.idr, tau=tau))

    def params(self) -> dict[str, Any]:
        """Flat parameters, for tables and MLflow."""
        return {**asdict(self.idr), **{k: getattr(self.intervention, k) for k in INTERVENTION_KEYS}}


def _fmt(value: Any) -> str:
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
        calibrated = params.get("tau") == CALIBRATED
        if calibrated:
            params["tau"] = 0.0  # placeholder until calibration
        try:
            idr = IDRConfig(**{k: params[k] for k in IDR_KEYS if k in params})
            iv = InterventionConfig(**{k: params[k] for k in INTERVENTION_KEYS if k in params})
        except (TypeError, ValueError) as e:
            raise ValueError(f"grid cell {dict(varied)}: {e}") from None
        if idr.mode == "baseline":
            cid = "baseline"
            varied = [("mode", "baseline")]
        else:
            cid = cell_name(varied)
        if cid in cells:
            if cid == "baseline":
                continue
            raise ValueError(f"grid gives two cells named {cid!r}: a value is listed twice")
        cells[cid] = Cell(cid, idr, iv, tuple(varied), calibrated_tau=calibrated and idr.refines)
    return list(cells.values())
