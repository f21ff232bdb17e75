"""LIBERO evaluation protocols by name: what each published number's evaluation pins.

Two conventions exist for the same simulator, and a checkpoint's score depends on which one runs:

============  =========================================  ==========================================
              ``openpi`` (openpi, OpenVLA-OFT; the paper)  ``lerobot`` (``lerobot-eval``, 0.6.x)
============  =========================================  ==========================================
seed          ``seed`` at every episode's reset            ``seed + e`` for episode ``e``
max steps     spatial 220, object 280, goal 300, 10: 520   spatial 280, object 280, goal 300,
                                                           10: 520, 90: 400
no-ops        10 (``[0]*6 + [-1]``, not counted)           10 (same)
render size   256 px                                       the checkpoint's declared size (as
                                                           ``--env.observation_height``); 360,
                                                           lerobot-eval's default, without one
replan        5 actions per inference (openpi's example)   the checkpoint's ``n_action_steps``
state         axis-angle in float64, then float32          axis-angle in float32 (lerobot's
                                                           ``LiberoProcessorStep`` arithmetic)
============  =========================================  ==========================================

Both: the suite's fixed init state ``e % 50`` for episode ``e``, images flipped 180 degrees, 20 Hz.
openpi seeds once per task and lets episode ``e``'s furniture follow ``e`` earlier hard resets;
a sharded run cannot replay that, so ``openpi`` reseeds each episode with ``seed`` (episode 0
matches openpi's; later ones differ in the cabinet/stove placement only).
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from workers.io_spec import Replan

SUITES: tuple[str, ...] = ("libero_spatial", "libero_object", "libero_goal", "libero_10")
SUPPORTED_SUITES: tuple[str, ...] = (*SUITES, "libero_90")
# our camera name -> (robosuite camera, key of its image in the raw observation)
CAMERAS: Mapping[str, tuple[str, str]] = {
    "agentview": ("agentview", "agentview_image"),
    "wrist": ("robot0_eye_in_hand", "robot0_eye_in_hand_image"),
}


@dataclass(frozen=True)
class NamedProtocol:
    """The defaults one evaluation convention pins (env params may override some, logged)."""

    name: str
    max_steps: Mapping[str, int]
    image_size: int | None  # None: the checkpoint's declared size
    default_image_size: int  # when nothing declares one
    num_noops: int
    seed_per_episode: bool  # reset seed is seed + episode_index (else seed)
    float32_state: bool  # axis-angle computed in float32 (else float64)
    replan: Replan


PROTOCOLS: Mapping[str, NamedProtocol] = {
    "openpi": NamedProtocol(
        name="openpi",
        max_steps={
            "libero_spatial": 220,
            "libero_object": 280,
            "libero_goal": 300,
            "libero_10": 520,
        },
        image_size=256,
        default_image_size=256,
        num_noops=10,
        seed_per_episode=False,
        float32_state=False,
        replan=5,
    ),
    "lerobot": NamedProtocol(
        name="lerobot",
        max_steps={
            "libero_spatial": 280,
            "libero_object": 280,
            "libero_goal": 300,
            "libero_10": 520,
            "libero_90": 400,
        },
        image_size=None,
        default_image_size=360,
        num_noops=10,
        seed_per_episode=True,
        float32_state=True,
        replan="chunk",
    ),
}


def named_protocol(name: str) -> NamedProtocol:
    if name not in PROTOCOLS:
        raise ValueError(
            f"env.params.protocol={name!r} is not a LIBERO protocol; choose one of "
            f"{list(PROTOCOLS)} (openpi: the paper's and OpenVLA-OFT's numbers; lerobot: "
            "lerobot-eval's)"
        )
    return PROTOCOLS[name]


def _did_you_mean(names: Sequence[str], known: Sequence[str]) -> str:
    close = [m for n in names for m in difflib.get_close_matches(n, known, n=2, cutoff=0.75)]
    return f" (did you mean {', '.join(dict.fromkeys(close))}?)" if close else ""


def _checked_names(
    suites: Sequence[str],
    cameras: Sequence[str],
    max_steps: Mapping[str, int] | None,
    known: Sequence[str] = SUPPORTED_SUITES,
) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """The suites and cameras as tuples (a lone name from a YAML override too), each known and
    distinct, and no unknown suite in ``max_steps``; else ValueError naming the param."""
    if isinstance(suites, str):  # a lone name from a YAML override
        suites = (suites,)
    if isinstance(cameras, str):
        cameras = (cameras,)
    unknown = [s for s in suites if s not in known]
    if not suites or unknown or len(set(suites)) != len(suites):
        raise ValueError(
            f"env.params.suites: {unknown or list(suites)} empty, unknown or repeated"
            f"{_did_you_mean(unknown, known)}; valid: {list(known)}"
        )
    stray = [s for s in max_steps or {} if s not in known]
    if stray:
        raise ValueError(
            f"env.params.max_steps: {stray} unknown suites{_did_you_mean(stray, known)}; "
            f"valid: {list(known)}"
        )
    bad = [c for c in cameras if c not in CAMERAS]
    if bad or len(set(cameras)) != len(cameras):
        raise ValueError(
            f"env.params.cameras={list(cameras)}: use distinct names from {list(CAMERAS)}"
        )
    return tuple(suites), tuple(cameras)


def _positive_int(name: str, value: object) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
        raise ValueError(f"env.params.{name} must be an int > 0, got {value!r}")


@dataclass(frozen=True)
class LiberoProtocol:
    """A named protocol with the env params' overrides applied, validated."""

    name: str
    suites: tuple[str, ...]
    image_size: int
    image_size_from_checkpoint: bool  # image_size is the default: the checkpoint may set it
    cameras: tuple[str, ...]
    num_noops: int
    max_steps: Mapping[str, int] = field(hash=False)
    flip_images: bool
    control_hz: float
    seed_per_episode: bool
    float32_state: bool
    replan: Replan

    @classmethod
    def from_params(
        cls,
        protocol: str,
        suites: Sequence[str],
        image_size: int | None,
        cameras: Sequence[str],
        num_noops: int | None,
        max_steps: Mapping[str, int] | None,
        flip_images: bool,
        control_hz: float,
        known: Sequence[str] = SUPPORTED_SUITES,
        base_of: Callable[[str], str] = str,
    ) -> LiberoProtocol:
        """``known``: the suite names the env has; ``base_of(suite)``: the suite whose protocol
        figures a suite takes where the protocol names none for it (LIBERO-PRO's
        ``libero_spatial_swap`` takes ``libero_spatial``'s max steps)."""
        named = named_protocol(protocol)
        suites, cameras = _checked_names(suites, cameras, max_steps, known)
        steps = {**named.max_steps, **(max_steps or {})}
        for suite in suites:
            if suite not in steps and base_of(suite) in steps:
                steps[suite] = steps[base_of(suite)]
            if suite not in steps:
                raise ValueError(
                    f"env.params.max_steps[{suite!r}] must be set: protocol {named.name!r} "
                    "has no figure for it"
                )
            _positive_int(f"max_steps[{suite!r}]", steps[suite])
        size = image_size if image_size is not None else named.image_size
        if size is not None:
            _positive_int("image_size", size)
        noops = named.num_noops if num_noops is None else num_noops
        if isinstance(noops, bool) or not isinstance(noops, int) or noops < 0:
            raise ValueError(f"env.params.num_noops must be an int >= 0, got {noops!r}")
        if isinstance(control_hz, bool) or not control_hz > 0:
            raise ValueError(f"env.params.control_hz must be > 0, got {control_hz!r}")
        return cls(
            name=named.name,
            suites=suites,
            image_size=named.default_image_size if size is None else size,
            image_size_from_checkpoint=size is None,
            cameras=cameras,
            num_noops=noops,
            max_steps={s: steps[s] for s in suites},
            flip_images=bool(flip_images),
            control_hz=float(control_hz),
            seed_per_episode=named.seed_per_episode,
            float32_state=named.float32_state,
            replan=named.replan,
        )

    def reset_seed(self, seed: int, episode_index: int) -> int:
        return seed + episode_index if self.seed_per_episode else seed

    def record(self) -> dict[str, Any]:
        """The protocol as logged with a run (run.json, MLflow params, the report)."""
        return {
            "name": self.name,
            "seed": "seed + episode" if self.seed_per_episode else "seed",
            "max_steps": dict(self.max_steps),
            "num_noops": self.num_noops,
            "image_size": self.image_size,
            "replan": self.replan,
            "state_arithmetic": "float32" if self.float32_state else "float64",
            "flip_images": self.flip_images,
            "control_hz": self.control_hz,
        }


def quat_to_axis_angle(quat_xyzw: np.ndarray) -> np.ndarray:
    """Axis-angle (3,) of a unit quaternion in robosuite's (x, y, z, w) order, in float64.

    The angle is 2 acos(w) in [0, 2 pi] (no wrap to [-pi, pi]): openpi's LIBERO state uses this
    convention, so a policy trained on its data sees the same numbers.
    """
    q = np.asarray(quat_xyzw, dtype=np.float64)
    w = float(np.clip(q[3], -1.0, 1.0))
    sin_half = np.sqrt(1.0 - w * w)
    if np.isclose(sin_half, 0.0):
        return np.zeros(3)
    return q[:3] * (2.0 * np.arccos(w) / sin_half)


def quat_to_axis_angle_f32(quat_xyzw: np.ndarray) -> np.ndarray:
    """The same axis-angle with lerobot's arithmetic: torch float32, the axis divided by
    sin(angle / 2) first and then scaled by the angle, zero below sin 1e-10.

    Written here rather than imported: lerobot's ``LiberoProcessorStep`` module takes ~28 s to
    import on this machine, too much for every env worker. The parity test checks this
    function against lerobot's own, bit for bit.
    """
    import torch

    q = torch.as_tensor(np.asarray(quat_xyzw)).reshape(1, 4).to(torch.float32)
    w = q[:, 3].clamp(-1.0, 1.0)
    sin_half = torch.sqrt(torch.clamp(1.0 - w * w, min=0.0))
    out = torch.zeros((1, 3), dtype=torch.float32)
    if bool(sin_half[0] > 1e-10):
        out = (q[:, :3] / sin_half.unsqueeze(1)) * (2.0 * torch.acos(w)).unsqueeze(1)
    return out[0].numpy()


def state_vector(raw_obs: Mapping[str, np.ndarray], float32_state: bool = False) -> np.ndarray:
    """(8,) float32: eef position, eef axis-angle, gripper finger positions."""
    quat = raw_obs["robot0_eef_quat"]
    aa = quat_to_axis_angle_f32(quat) if float32_state else quat_to_axis_angle(quat)
    return np.concatenate([raw_obs["robot0_eef_pos"], aa, raw_obs["robot0_gripper_qpos"]]).astype(
        np.float32
    )
