"""Scene perturbations: the same task with the camera moved, the light dimmed, the table
recoloured, the sensor noisy or blurred, or the objects' start jittered.

A perturbation is ``kind:severity`` (``camera_shift:0.12``) or ``none``. It is a property of
a task: ``env.perturbations`` crosses the run's tasks with a list of them, and a task id names
its perturbation after an ``@`` (``pick_color@camera_shift:0.12``); the unperturbed task keeps
its plain id, so ``none`` is today's episode to the bit. Paired comparisons therefore pair a
cell with its reference on the same perturbed task, episode and seed, and every table of the
report breaks results down by perturbation for free.

Image kinds (``image_noise``, ``image_blur``) act at the sensor, on every camera's rendered
image, for any suite (:class:`PerturbedEnv` applies them). Scene kinds act on the simulator
after its reset and before the first observation, in suites that say they can
(``perturbation_kinds``: the tabletop and LIBERO, both MuJoCo). Every random draw is seeded by
(seed, task, episode, perturbation): an episode is the same wherever and whenever it runs.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

SEP = "@"  # task id @ perturbation


@dataclass(frozen=True)
class Kind:
    low: float  # severity range, exclusive low / inclusive high
    high: float
    unit: str
    scene: bool  # applied by the env to its simulator (else at the sensor, by PerturbedEnv)
    what: str


KINDS: dict[str, Kind] = {
    "camera_shift": Kind(0.0, 0.3, "m", True, "the main camera moved sideways by SEVERITY m"),
    "camera_pitch": Kind(0.0, 30.0, "deg", True, "the main camera pitched down by SEVERITY deg"),
    "light_dim": Kind(0.0, 1.0, "fraction", True, "every light's intensity scaled by 1 - SEVERITY"),
    "table_color": Kind(
        0.0, 1.0, "fraction", True, "the table's colour blended toward dark brown by SEVERITY"
    ),
    "init_jitter": Kind(
        0.0, 0.02, "m", True, "each object's start moved by up to SEVERITY m in x and y"
    ),
    "image_noise": Kind(0.0, 1.0, "fraction of 255", False, "Gaussian pixel noise, std SEVERITY"),
    "image_blur": Kind(0.0, 5.0, "px", False, "Gaussian blur of std SEVERITY px"),
}
SCENE_KINDS = tuple(k for k, v in KINDS.items() if v.scene)
IMAGE_KINDS = tuple(k for k, v in KINDS.items() if not v.scene)
SYNTAX = (
    "write none or KIND:SEVERITY with KIND one of "
    + ", ".join(f"{k} ({v.low:g} < SEVERITY <= {v.high:g} {v.unit})" for k, v in KINDS.items())
    + ", e.g. camera_shift:0.12"
)


@dataclass(frozen=True)
class Perturbation:
    kind: str
    severity: float

    @property
    def text(self) -> str:
        return f"{self.kind}:{self.severity:g}"

    @property
    def scene(self) -> bool:
        return KINDS[self.kind].scene

    def rng(self, seed: int, task_id: str, episode_index: int, *more: int) -> np.random.Generator:
        """The perturbation's random stream for one episode (and, with ``more``, one step and
        camera): a pure function of its arguments."""
        key = zlib.crc32(f"{task_id}{SEP}{self.text}".encode())
        return np.random.default_rng([seed, episode_index, key, *more])


def parse(value: Any) -> Perturbation | None:
    """``none`` / None -> None; ``kind:severity`` or ``{kind, severity}`` -> a Perturbation;
    ValueError naming the allowed kinds and ranges otherwise."""
    if value is None or value == "none":
        return None
    if isinstance(value, Mapping):
        kind, severity = value.get("kind"), value.get("severity")
        extra = set(value) - {"kind", "severity"}
        if extra:
            raise ValueError(f"perturbation {dict(value)}: unknown keys {sorted(extra)}; {SYNTAX}")
    elif isinstance(value, str) and ":" in value:
        kind, _, severity = value.partition(":")
    else:
        raise ValueError(f"perturbation {value!r}: {SYNTAX}")
    if kind not in KINDS:
        raise ValueError(f"perturbation kind {kind!r} is unknown; {SYNTAX}")
    try:
        sev = float(severity)
    except (TypeError, ValueError):
        raise ValueError(f"perturbation {value!r}: severity must be a number; {SYNTAX}") from None
    k = KINDS[kind]
    if not (k.low < sev <= k.high):
        raise ValueError(
            f"perturbation {kind}:{sev:g}: severity out of range, {k.low:g} < severity <= "
            f"{k.high:g} ({k.unit}: {k.what})"
        )
    return Perturbation(kind, sev)


def split_task(task_id: str) -> tuple[str, Perturbation | None]:
    """``pick_color@camera_shift:0.12`` -> (``pick_color``, the perturbation)."""
    base, sep, rest = task_id.partition(SEP)
    return base, (parse(rest) if sep else None)


def join_task(task_id: str, p: Perturbation | None) -> str:
    return task_id if p is None else f"{task_id}{SEP}{p.text}"


def perturbation_of(task_id: str) -> str:
    """The perturbation a task id names, as text (``none`` for a plain id)."""
    _, p = split_task(task_id)
    return "none" if p is None else p.text


# -- at the sensor --------------------------------------------------------------------------------


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
