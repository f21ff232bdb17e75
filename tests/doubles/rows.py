"""Typed rows for tests that write hand-made episodes: every required column defaulted, the
ones a test cares about given. An unknown column is refused (TypeError), as in the real rows."""

from __future__ import annotations

import math
from typing import Any

from workers.episode.rows import EpisodeResult, EpisodeRow, StepRow

EPISODE_DEFAULTS: dict[str, Any] = {
    "run_id": "r",
    "cell_id": "baseline",
    "mode": "baseline",
    "guidance": "visual",
    "strategy": "zero",
    "alpha": 0.08,
    "beta": 0.05,
    "lam": 0.1,
    "tau": 7.0,
    "backbone": "fake_marker",
    "suite": "s",
    "task_id": "t",
    "task_name": "t",
    "episode_index": 0,
    "seed": 0,
    "max_steps": 10,
    "subtasks_total": 1,
}
STEP_DEFAULTS: dict[str, Any] = {
    "run_id": "r",
    "cell_id": "baseline",
    "task_id": "t",
    "episode_index": 0,
    "inference_index": 0,
    "step": 0,
}


def _clean(values: dict[str, Any]) -> dict[str, Any]:
    """NaN (what a pandas record holds for a missing value) -> None."""
    return {k: None if isinstance(v, float) and math.isnan(v) else v for k, v in values.items()}


def episode_row(**values: Any) -> EpisodeRow:
    return EpisodeRow(**{**EPISODE_DEFAULTS, **_clean(values)})


def step_row(**values: Any) -> StepRow:
    return StepRow(**{**STEP_DEFAULTS, **_clean(values)})


def result(episode: dict[str, Any], steps: list[dict[str, Any]] = ()) -> EpisodeResult:
    return EpisodeResult(episode_row(**episode), [step_row(**s) for s in steps])
