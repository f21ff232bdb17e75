"""The perturbation grammar: ``kind:severity`` (``camera_shift:0.12``) or ``none``, its kinds and
ranges, and task ids that name one after an ``@`` (``pick_color@camera_shift:0.12``). Pure data:
config validation, the pre-flight and the report import it without any image or simulator code.
"""

from __future__ import annotations

import zlib
from collections.abc import Mapping
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
    "camera_pitch": Kind(0.0, 30.0, "deg", True, "the main camera pitched up by SEVERITY deg"),
    "light_dim": Kind(0.0, 1.0, "fraction", True, "every light's intensity scaled by 1 - SEVERITY"),
    "table_color": Kind(
        0.0, 1.0, "fraction", True, "the table's colour blended toward dark brown by SEVERITY"
    ),
    "init_jitter": Kind(
        0.0, 0.02, "m", True, "each object's start moved by up to SEVERITY m in x and y"
    ),
    "distractors": Kind(0.0, 4.0, "objects", True, "SEVERITY extra grey cubes on the table"),
    "image_noise": Kind(0.0, 1.0, "fraction of 255", False, "Gaussian pixel noise, std SEVERITY"),
    "image_blur": Kind(0.0, 5.0, "px", False, "Gaussian blur of std SEVERITY px"),
    # the image-zeroed control: the policy sees black (1) or darkened (< 1) images at every step,
    # executed, not only in the diagnosis's counterfactual pass
    "image_blackout": Kind(
        0.0, 1.0, "fraction", False, "pixels scaled by 1 - SEVERITY (1: a black image)"
    ),
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
    if k.unit == "objects" and not sev.is_integer():
        raise ValueError(f"perturbation {kind}:{sev:g}: a count of objects is a whole number")
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
