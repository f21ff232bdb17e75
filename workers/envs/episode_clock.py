"""Step counting, the horizon and call order of an env's episodes, in one place.

Gymnasium keeps these out of its envs, in the ``TimeLimit`` and ``OrderEnforcing`` wrappers.
Our suites hold one :class:`EpisodeClock` each: ``start`` at a reset, ``take`` on each step's
action (it checks shape, finiteness and order, then counts the step), and ``status`` to build
the frozen record the reset or step returns. What a suite decides itself is only what differs
between suites: its instruction, its success, and whether it ends an episode early.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from workers.envs.base import EpisodeInfo, EpisodeStatus, TaskSpec, checked_action


class EpisodeClock:
    """The step count and call order of one env; ``done`` at ``task.max_steps`` or when the
    suite ends the episode (``ended``)."""

    def __init__(self, action_dim: int) -> None:
        self.action_dim = int(action_dim)
        self.task: TaskSpec | None = None
        self.steps = 0
        self.done = False

    def start(self, task: TaskSpec) -> None:
        """A reset to ``task``: the count back to 0."""
        self.task, self.steps, self.done = task, 0, False

    def take(self, action: Any) -> np.ndarray:
        """``action`` as float64 (action_dim,), counted as the next step; ValueError for a
        wrong shape or a NaN / inf, RuntimeError before a reset or after done (nothing counted)."""
        a = checked_action(action, self.action_dim, self.task is not None, self.done)
        self.steps += 1
        return a

    def status(
        self,
        instruction: str,
        success: bool,
        *,
        ended: bool = False,
        subtasks_done: int | None = None,
        info: EpisodeInfo | None = None,
        task_id: str | None = None,
    ) -> EpisodeStatus:
        """The record after a reset or a step. ``ended``: the suite ended the episode before
        the horizon (a success where success ends it, a failed chain); ``subtasks_done``
        defaults to ``int(success)``; ``task_id`` defaults to the task's."""
        if self.task is None:
            raise RuntimeError("no task: call reset() first")
        self.done = bool(ended) or self.steps >= self.task.max_steps
        return EpisodeStatus(
            task_id=task_id or self.task.task_id,
            instruction=str(instruction),
            steps=self.steps,
            success=bool(success),
            done=self.done,
            subtasks_done=int(success) if subtasks_done is None else int(subtasks_done),
            info=info or EpisodeInfo(),
        )
