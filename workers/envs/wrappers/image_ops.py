"""Image perturbations at the sensor (``image_noise``, ``image_blur``, ``image_blackout``): pure
functions of a rendered uint8 image, and a lazy mapping that applies one to every camera."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any

import numpy as np

from workers.envs.wrappers.perturbation_grammar import Perturbation


def perturb_image(image: np.ndarray, p: Perturbation, rng: np.random.Generator) -> np.ndarray:
    """``image`` (uint8 H x W x C) with an image kind applied; a new array."""
    if p.kind == "image_noise":
        noisy = image.astype(np.float32) + rng.normal(0.0, 255.0 * p.severity, image.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    if p.kind == "image_blur":
        from scipy.ndimage import gaussian_filter

        sigma = (p.severity, p.severity, 0)[: image.ndim]
        out = gaussian_filter(image.astype(np.float32), sigma=sigma, mode="nearest")
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    if p.kind == "image_blackout":
        out = image.astype(np.float32) * (1.0 - p.severity)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    raise ValueError(f"{p.kind} is not an image perturbation")


class PerturbedImages(Mapping[str, np.ndarray]):
    """A lazy image mapping whose images come out perturbed (each camera drawn once)."""

    def __init__(self, images: Mapping[str, np.ndarray], p: Perturbation, rng_for: Any) -> None:
        self._images, self._p, self._rng_for = images, p, rng_for
        self._done: dict[str, np.ndarray] = {}

    def __getitem__(self, camera: str) -> np.ndarray:
        if camera not in self._done:
            image = self._images[camera]
            self._done[camera] = perturb_image(image, self._p, self._rng_for(camera))
        return self._done[camera]

    def __iter__(self) -> Iterator[str]:
        return iter(self._images)

    def __len__(self) -> int:
        return len(self._images)
