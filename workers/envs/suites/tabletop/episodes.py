"""A tabletop episode: its seeded layout and instruction, and the rules that score it (what
counts as picked, stacked, or put in the bin in order). numpy only: the scene is ``sim``'s.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from workers.envs.suites.tabletop.layout import BIN_CENTER, BIN_INNER_HALF, CUBE_HALF, TABLE_TOP_Z

LIFT_HEIGHT = 0.05  # pick_color: the cube's bottom this far above the table counts as picked


@dataclass
class Episode:
    """One episode's layout and what it has done so far."""

    task_id: str
    colors: tuple[str, ...]
    cube_xy: np.ndarray
    instruction: str
    targets: list[int]  # pick: [cube]; stack: [top, bottom]; organize: the order
    subtasks_done: int = 0
    last_progress_step: int = 0
    success: bool = False
    failed: str | None = None  # why the episode ended early (text)
    failed_cause: str | None = None  # the same as a stable code: wrong_order | subtask_budget
    init_state_id: str = ""
    scene_key: str = ""  # which scene: the task's, or the task's with distractors

    def __post_init__(self) -> None:
        self.scene_key = self.scene_key or self.task_id

    placed: set[int] = field(default_factory=set)


def sample_xy(
    rng: np.random.Generator,
    n: int,
    x: tuple[float, float],
    y: tuple[float, float],
    min_dist: float,
) -> np.ndarray:
    """n points in the box, pairwise at least min_dist apart (rejection sampling)."""
    for _ in range(1000):
        pts = np.stack([rng.uniform(*x, size=n), rng.uniform(*y, size=n)], axis=1)
        d = np.linalg.norm(pts[:, None] - pts[None], axis=-1) + np.eye(n) * 1e9
        if d.min() >= min_dist:
            return pts
    raise RuntimeError("could not place the cubes apart; widen the placement range")


def free_spots(rng: np.random.Generator, taken: np.ndarray, n: int, with_bin: bool) -> np.ndarray:
    """n (x, y) spots on the table at least a cube's spacing from the task's cubes, each
    other and (organize) the bin: where the distractors go."""
    spots: list[np.ndarray] = []
    for _ in range(10_000):
        if len(spots) == n:
            return np.array(spots)
        xy = np.array([rng.uniform(-0.15, 0.15), rng.uniform(-0.28, 0.14)])
        others = [*taken, *spots]
        if min(np.linalg.norm(np.asarray(others) - xy, axis=1)) < 0.07:
            continue
        if with_bin and np.abs(xy - BIN_CENTER).max() < BIN_INNER_HALF + 0.06:
            continue
        spots.append(xy)
    raise RuntimeError(f"could not place {n} distractors apart from the task's cubes")


def new_episode(
    task_id: str, task_index: int, colors: tuple[str, ...], episode_index: int, seed: int
) -> Episode:
    """The episode's layout, instruction and targets, drawn from (seed, episode, task): every
    cell of a grid sees the same scenes."""
    rng = np.random.default_rng([seed, episode_index, task_index, 20])
    if task_id == "organize":
        xy = sample_xy(rng, 5, (-0.13, 0.13), (-0.27, 0.06), 0.075)
        order = [int(i) for i in rng.permutation(5)]
        names = [colors[i] for i in order]
        text = f"put the {', '.join(names[:-1])} and {names[-1]} cubes in the bin, in that order"
        targets = order
    else:
        xy = sample_xy(rng, 3, (-0.13, 0.13), (-0.25, 0.12), 0.08)
        if task_id == "pick_color":
            targets = [int(rng.integers(3))]
            text = f"pick up the {colors[targets[0]]} cube"
        else:
            top, bottom = (int(i) for i in rng.permutation(3)[:2])
            targets = [top, bottom]
            text = f"stack the {colors[top]} cube on the {colors[bottom]} cube"
    return Episode(
        task_id, colors, xy, text, targets, init_state_id=f"{task_id}/{seed}/{episode_index}"
    )


def update_progress(ep: Episode, scene: Any, subtask_budget: int, steps: int) -> None:
    """``ep``'s success, subtasks and failure after step ``steps``, from the scene's cubes."""
    pos = scene.cube_positions()

    if ep.task_id == "pick_color":
        if pos[ep.targets[0], 2] - CUBE_HALF > TABLE_TOP_Z + LIFT_HEIGHT:
            ep.success, ep.subtasks_done = True, 1
    elif ep.task_id == "stack_color":
        top, bottom = ep.targets
        d = pos[top] - pos[bottom]
        on_top = np.linalg.norm(d[:2]) < 0.025 and 1.6 * CUBE_HALF < d[2] < 2.4 * CUBE_HALF
        if on_top and not scene.is_grasped(top) and not scene.is_grasped(bottom):
            ep.success, ep.subtasks_done = True, 1
    else:
        inside = (np.abs(pos[:, :2] - BIN_CENTER).max(axis=1) < BIN_INNER_HALF) & (
            pos[:, 2] < TABLE_TOP_Z + 3 * CUBE_HALF
        )
        for i in np.flatnonzero(inside):
            i = int(i)
            if i in ep.placed or scene.is_grasped(i):
                continue
            expected = ep.targets[ep.subtasks_done]
            if i != expected:
                ep.failed = (
                    f"{ep.colors[i]} cube put in the bin before the {ep.colors[expected]} one"
                )
                ep.failed_cause = "wrong_order"
                return
            ep.placed.add(i)
            ep.subtasks_done += 1
            ep.last_progress_step = steps
            if ep.subtasks_done == 5:
                ep.success = True
                return
        if steps - ep.last_progress_step >= subtask_budget:
            ep.failed = f"subtask {ep.subtasks_done + 1} not done within {subtask_budget} steps"
            ep.failed_cause = "subtask_budget"
