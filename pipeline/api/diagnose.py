"""``diagnose``: a policy's reliance on vision and on proprioception on given frames (open loop).

The measure is the harness's own, on frames instead of an episode: the policy behind the
harness's lerobot backbone (``workers.backbones.lerobot.adapter.LerobotBackbone``), wrapped by
``workers.policy.wrapper.IDRWrapper`` in mode ``diagnose`` (three passes sharing one noise draw:
factual, do(V), do(S); the executed action is the base's), with the default config's
interventions (``zero``; do(V) on raw pixels, do(S) about the dataset mean state). Per frame
E_img = ||a - a_do(V)||, E_prop = ||a - a_do(S)|| over the whole chunk and
R_img = E_img / (E_img + E_prop + eps), exactly the step table's columns of a closed-loop run.

Frames: ``{"images": {camera: (N, 3, H, W) float in [0, 1]}, "state": (N, S), "instruction":
str | list[str]}`` (numpy or torch), or a list of single frames of the same keys without the
batch dim. Extra keys (a frame's progress, its source) are ignored: results come in frame order.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from idr_core.interventions import InterventionConfig

from pipeline.errors import ConfigError
from workers.backbones.base import Observation

if TYPE_CHECKING:
    from workers.policy.wrapper import IDRWrapper

#: the interventions of conf/default.yaml (``intervention:``), which diagnose uses by default
DEFAULT_INTERVENTION = InterventionConfig(
    strategy="zero", image_space="raw", state_space="centered"
)


@dataclass(frozen=True)
class Diagnosis:
    """E_img, E_prop and R_img per frame (in frame order) and their means."""

    e_img: np.ndarray  # (N,) ||a_base - a_no_img|| over the chunk, in the policy's action units
    e_prop: np.ndarray  # (N,) ||a_base - a_no_prop||
    r_img: np.ndarray  # (N,) in [0, 1]
    e_img_mean: float
    e_prop_mean: float
    r_img_mean: float  # the mean of the per-frame R_img
    r_img_ci: tuple[
        float, float
    ]  # percentile bootstrap 95% interval of r_img_mean (frames resampled)
    policy: str  # the backbone's name, e.g. ``lerobot:tiny_vla``
    intervention: InterventionConfig

    @property
    def n(self) -> int:
        return int(self.e_img.shape[0])


def frames_observation(frames: Mapping[str, Any] | Sequence[Mapping[str, Any]]) -> Observation:
    """The frames as one batch (ConfigError for frames that do not fit the format)."""
    if isinstance(frames, Observation):
        frames.validate()
        return frames
    if isinstance(frames, Sequence) and not isinstance(frames, str | bytes):
        if not frames:
            raise ConfigError("frames: an empty list; give at least one frame")
        return _stack([_one_frame(f, i) for i, f in enumerate(frames)])
    if not isinstance(frames, Mapping):
        raise ConfigError(
            f"frames: a dict of images / state / instruction or a list of such frames, not "
            f"{type(frames).__name__}"
        )
    missing = [k for k in ("images", "state", "instruction") if k not in frames]
    if missing:
        raise ConfigError(f"frames: missing {missing}; give images, state and instruction")
    images = frames["images"]
    if not isinstance(images, Mapping) or not images:
        raise ConfigError("frames['images']: a dict camera -> (N, 3, H, W) array")
    imgs = {str(cam): _array(x, f"frames['images'][{cam!r}]") for cam, x in images.items()}
    state = _array(frames["state"], "frames['state']")
    if state.ndim != 2:
        raise ConfigError(f"frames['state'] has shape {state.shape}; expected (N, S)")
    n = state.shape[0]
    text = frames["instruction"]
    instructions = [text] * n if isinstance(text, str) else [str(t) for t in text]
    for cam, x in imgs.items():
        if x.ndim != 4 or x.shape[1] != 3:
            raise ConfigError(
                f"frames['images'][{cam!r}] has shape {x.shape}; expected (N, 3, H, W)"
            )
        if x.size and (x.min() < 0 or x.max() > 1):
            raise ConfigError(
                f"frames['images'][{cam!r}] has values in [{x.min():.3g}, {x.max():.3g}]; "
                "images are floats in [0, 1] (divide uint8 pixels by 255)"
            )
    obs = Observation(imgs, state, instructions)
    try:
        obs.validate()
    except ValueError as e:
        raise ConfigError(f"frames: {e}") from None
    return obs


def _array(x: Any, what: str) -> np.ndarray:
    if hasattr(x, "detach"):  # a torch tensor
        x = x.detach().cpu().numpy()
    arr = np.asarray(x)
    if not np.issubdtype(arr.dtype, np.number):
        raise ConfigError(f"{what}: numbers expected, got dtype {arr.dtype}")
    return arr.astype(np.float32, copy=False)


def _one_frame(frame: Any, i: int) -> Observation:
    if not isinstance(frame, Mapping) or not isinstance(frame.get("images"), Mapping):
        raise ConfigError(
            f"frames[{i}]: a dict with images (camera -> (3, H, W)), state, instruction"
        )
    batched = {
        "images": {
            cam: _array(x, f"frames[{i}]['images'][{cam!r}]")[None]
            for cam, x in frame["images"].items()
        },
        "state": _array(frame.get("state", []), f"frames[{i}]['state']")[None],
        "instruction": [str(frame.get("instruction", ""))],
    }
    return frames_observation(batched)


def _stack(obs: list[Observation]) -> Observation:
    cams = set(obs[0].images)
    for i, o in enumerate(obs):
        if set(o.images) != cams:
            raise ConfigError(
                f"frames[{i}] has cameras {sorted(o.images)}, frames[0] {sorted(cams)}"
            )
    try:
        images = {c: np.concatenate([o.images[c] for o in obs]) for c in cams}
        state = np.concatenate([o.state for o in obs])
    except ValueError as e:
        raise ConfigError(f"frames: the frames differ in shape ({e})") from None
    return Observation(images, state, [t for o in obs for t in o.instruction])


def lerobot_backbone(
    policy_or_checkpoint: Any,
    *,
    device: str | None = None,
    camera_map: dict[str, str] | None = None,
    preprocessor: Any = None,
    postprocessor: Any = None,
) -> Any:
    """The harness's lerobot backbone for a checkpoint folder, or for a lerobot policy object
    already in memory (its processors: given, else its checkpoint's saved ones from
    ``policy.config.pretrained_path``)."""
    from workers.backbones.lerobot.adapter import LerobotBackbone

    if isinstance(policy_or_checkpoint, str | Path):
        try:
            LerobotBackbone.check_params({"path": str(policy_or_checkpoint)})
        except ValueError as e:
            raise ConfigError(str(e)) from None
        return LerobotBackbone(
            str(policy_or_checkpoint), device=device or "cpu", camera_map=camera_map
        )
    if not hasattr(policy_or_checkpoint, "predict_action_chunk") or not hasattr(
        policy_or_checkpoint, "config"
    ):
        raise ConfigError(
            "policy_or_checkpoint: a lerobot checkpoint folder or a lerobot PreTrainedPolicy, not "
            f"{type(policy_or_checkpoint).__name__}"
        )
    from pipeline.api.policy_backbone import PolicyBackbone

    return PolicyBackbone(
        policy_or_checkpoint,
        preprocessor=preprocessor,
        postprocessor=postprocessor,
        device=device,
        camera_map=camera_map,
    )


def diagnose(
    policy_or_checkpoint: str | Path | Any,
    frames: Mapping[str, Any] | Sequence[Mapping[str, Any]],
    *,
    intervention: InterventionConfig = DEFAULT_INTERVENTION,
    batch_size: int = 32,
    seed: int = 0,
    n_boot: int = 2000,
    device: str | None = None,
    camera_map: dict[str, str] | None = None,
    preprocessor: Any = None,
    postprocessor: Any = None,
) -> Diagnosis:
    """E_img, E_prop and R_img of a policy on ``frames`` (module docstring: the format).

    ``policy_or_checkpoint``: a lerobot checkpoint folder, or a lerobot policy in memory (a
    training loop's; its pre/post-processors given, else loaded from its
    ``config.pretrained_path``). Frames go through in batches of ``batch_size``; batch ``i``
    draws its noise from ``seed + i`` (shared by its three passes), so a sampling policy's
    values are reproducible for one batching. ``camera_map``: frame camera -> the policy's image
    key suffix (default: the same names). ``n_boot``: bootstrap resamples of the interval.
    Bad input raises ConfigError before the policy is loaded."""
    from pipeline.results.aggregate import bootstrap_mean_ci

    if batch_size < 1:
        raise ConfigError(f"batch_size={batch_size} must be >= 1")
    obs = frames_observation(frames)
    backbone = lerobot_backbone(
        policy_or_checkpoint,
        device=device,
        camera_map=camera_map,
        preprocessor=preprocessor,
        postprocessor=postprocessor,
    )
    try:
        parts = _run(diagnose_wrapper(backbone, intervention), obs, batch_size, seed)
    finally:
        close = getattr(backbone, "close", None)
        if close is not None:  # an in-memory policy's processors get their hooks back
            close()
    e_img, e_prop, r_img = (np.concatenate([p[k] for p in parts]) for k in range(3))
    return Diagnosis(
        e_img=e_img,
        e_prop=e_prop,
        r_img=r_img,
        e_img_mean=float(e_img.mean()),
        e_prop_mean=float(e_prop.mean()),
        r_img_mean=float(r_img.mean()),
        r_img_ci=bootstrap_mean_ci(r_img, n_boot=n_boot, seed=seed),
        policy=str(backbone.name),
        intervention=intervention,
    )


def _run(
    wrapper: IDRWrapper, obs: Observation, batch_size: int, seed: int
) -> list[tuple[np.ndarray, ...]]:
    """(e_img, e_prop, r_img) per batch of ``batch_size`` frames, batch ``i`` seeded ``seed + i``."""
    parts = []
    for i, start in enumerate(range(0, obs.batch_size, batch_size)):
        rows = slice(start, start + batch_size)
        part = Observation(
            {c: x[rows] for c, x in obs.images.items()}, obs.state[rows], obs.instruction[rows]
        )
        wrapper.reset()
        diag = wrapper.infer(part, step_seed=seed + i).diag
        if diag is None:  # mode diagnose always runs the counterfactual passes
            raise RuntimeError("the diagnose wrapper returned no diagnostics")
        parts.append(tuple(_numpy(v) for v in (diag.e_img, diag.e_prop, diag.r_img)))
    return parts


def diagnose_wrapper(
    backbone: Any, intervention: InterventionConfig = DEFAULT_INTERVENTION
) -> IDRWrapper:
    """The harness's IDR wrapper of ``backbone`` in mode ``diagnose``."""
    from idr_core.refiner import RefinerConfig

    from workers.policy.wrapper import IDRWrapper

    try:
        return IDRWrapper(backbone, RefinerConfig(mode="diagnose"), intervention)
    except ValueError as e:
        raise ConfigError(str(e)) from None


def _numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64).reshape(-1)
