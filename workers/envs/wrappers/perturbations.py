"""Scene perturbations: the same task with the camera moved, the light dimmed, the table
recoloured, the sensor noisy or blurred, or the objects' start jittered.

A perturbation is ``kind:severity`` (``camera_shift:0.12``) or ``none``. It is a property of
a task: ``env.perturbations`` crosses the run's tasks with a list of them, and a task id names
its perturbation after an ``@`` (``pick_color@camera_shift:0.12``); the unperturbed task keeps
its plain id, so ``none`` is today's episode to the bit. Paired comparisons therefore pair a
cell with its reference on the same perturbed task, episode and seed, and every table of the
report breaks results down by perturbation for free.

Image kinds (``image_noise``, ``image_blur``, ``image_blackout``) act at the sensor, on every camera's rendered
image, for any suite (:class:`PerturbedEnv` applies them). Scene kinds act on the simulator
after its reset and before the first observation, in suites that say they can
(``perturbation_kinds``: the tabletop and LIBERO, both MuJoCo; distractors: the tabletop). Every random draw is seeded by
(seed, task, episode, perturbation): an episode is the same wherever and whenever it runs.

The grammar lives in ``perturbation_grammar``, the image operations in ``image_ops``, the
MuJoCo scene edits in ``workers.envs.mujoco.scene_edits``; this module holds the wrapper.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable
from typing import Any

import numpy as np

from workers.envs.wrappers.image_ops import PerturbedImages, perturb_image
from workers.envs.wrappers.perturbation_grammar import (
    IMAGE_KINDS,
    Perturbation,
    join_task,
    split_task,
)


def perturbed_task(task: Any, p: Perturbation | None) -> Any:
    """``task`` (a TaskSpec) under ``p``: its id names the perturbation; None: unchanged."""
    from dataclasses import replace

    if p is None:
        return task
    return replace(
        task,
        task_id=join_task(task.task_id, p),
        name=f"{task.name} [{p.text}]",
        perturbation=p.kind,
        severity=p.severity,
    )


class PerturbedEnv:
    """An env whose tasks are crossed with perturbations (ids ``task@kind:severity``).

    Scene kinds go to the env (its optional ``set_perturbation``, before its reset); image
    kinds are applied here to every image the env renders, lazily, seeded per (seed, task,
    episode, perturbation, step, camera), its object-hidden images included. Everything else
    is the wrapped env's."""

    def __init__(self, env: Any, perturbations: list[Perturbation | None]) -> None:
        self._env = env
        self._perturbations = list(perturbations) or [None]
        self._p: Perturbation | None = None
        self._episode: tuple[str, int, int] = ("", 0, 0)
        # the image kind's draw of the current observation, per camera (object_hidden_images)
        self._rng_for: Callable[[str], np.random.Generator] | None = None

    def __getattr__(self, name: str) -> Any:  # the env's members (optional ones included)
        return getattr(self._env, name)

    def tasks(self) -> list[Any]:
        return [perturbed_task(t, p) for t in self._env.tasks() for p in self._perturbations]

    def reset(self, task_id: str, episode_index: int, seed: int) -> Any:
        from workers.envs.base import suite_hooks, suite_info

        base, p = split_task(task_id)
        setter = suite_hooks(self._env).set_perturbation
        if p is not None and p.scene:
            if setter is None or p.kind not in suite_info(self._env).perturbation_kinds:
                raise ValueError(
                    f"{task_id}: suite {getattr(self._env, 'suite', '?')!r} cannot apply "
                    f"{p.kind}; image kinds ({', '.join(IMAGE_KINDS)}) work with any suite"
                )
            setter(p)
        elif setter is not None:
            setter(None)
        obs = self._env.reset(base, episode_index, seed)
        self._p, self._episode = p, (task_id, episode_index, seed)
        return self._wrap(obs)

    def step(self, action: np.ndarray) -> Any:
        return self._wrap(self._env.step(action))

    def _wrap(self, obs: Any) -> Any:
        from dataclasses import replace

        from workers.envs.base import episode_status

        p = self._p
        task_id, episode, seed = self._episode
        status = episode_status(self._env, obs)
        obs = replace(obs, status=replace(status, task_id=task_id))  # the perturbed task's id
        self._rng_for = None
        if p is None or p.scene:
            return obs
        step = status.steps

        def rng_for(camera: str) -> np.random.Generator:
            return p.rng(seed, task_id, episode, step, zlib.crc32(camera.encode()))

        self._rng_for = rng_for
        return replace(obs, images=PerturbedImages(obs.images, p, rng_for))

    def object_hidden_images(self) -> dict[str, np.ndarray]:
        """The env's ``object_hidden_images`` of the current observation, under this episode's
        perturbation as that observation's images are: scene kinds are in the env's render
        already; an image kind is applied here with the same draw per camera (seeded by the same
        seed, task, episode, step and camera), so image_noise adds the very noise the
        observation got and the two images differ only where the objects are."""
        from workers.envs.base import suite_info

        if not suite_info(self._env).renders_hidden_objects:
            raise NotImplementedError(
                f"suite {getattr(self._env, 'suite', '?')!r} renders no object-hidden images "
                "(SuiteInfo.renders_hidden_objects is False)"
            )
        images = self._env.object_hidden_images()
        p, rng_for = self._p, self._rng_for
        if p is None or p.scene or rng_for is None:
            return images
        return {cam: perturb_image(img, p, rng_for(cam)) for cam, img in images.items()}
