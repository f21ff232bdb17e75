"""The infer stage's interventions do(V = v*) and do(S = s*), separate from the refiner.

A strategy turns an input tensor into its counterfactual value:

- ``zero`` (the paper's): an all-zero tensor of the same shape.
- ``mean``: every element replaced by the sample's mean value (per sample, over all
  non-batch dims), i.e. a uniform image of the sample's mean intensity / a constant state.
- ``gaussian``: the input plus Gaussian noise whose std is ``noise_scale`` (default 50%) of the
  sample's own std, drawn from a seeded generator so that reruns are identical.

``do(V)`` applies to every camera image of an observation, ``do(S)`` to the state vector.
*Where* in a processing chain it applies is an option recorded with every run:

- ``raw``: on the observation the env produced (a black image in [0, 1]; the state's origin).
- ``centered`` (do(S) only; the default): on the raw state about the base's dataset mean, in
  physical units: ``zero`` gives the mean state of the data the base was trained on, read from
  its checkpoint's normalizer statistics, whatever its normalizer (MEAN_STD, MIN_MAX, IDENTITY).
  So every architecture gets the same counterfactual; under MEAN_STD it is ``normalized``'s zero
  exactly. A base without dataset statistics (a scripted expert, a fake) is centered at zero.
- ``normalized``: after the backbone's normalizer, where zero means the dataset mean under
  MEAN_STD, the middle of the range under MIN_MAX and the raw origin under IDENTITY.

Raw and centered interventions are applied by the IDR wrapper (or the idr policy's processor
step); normalized-space ones are delegated to backbones that support them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, get_args

import numpy as np

from idr_core.tensors import is_torch

Strategy = Literal["zero", "mean", "gaussian"]
Space = Literal["raw", "centered", "normalized"]

STRATEGIES: tuple[str, ...] = get_args(Strategy)
SPACES: tuple[str, ...] = get_args(Space)


@dataclass(frozen=True)
class InterventionConfig:
    """How the counterfactual inputs are made; recorded with every run."""

    strategy: str = "zero"  # one of STRATEGIES
    image_space: str = "raw"  # where do(V) applies: raw [0,1] pixels (a black image for `zero`)
    state_space: str = "centered"  # where do(S) applies; `normalized` needs backbone support
    noise_scale: float = 0.5  # gaussian: noise std as a fraction of the input's std
    seed: int = 0  # gaussian: base seed; the wrapper folds in the step index

    def __post_init__(self) -> None:
        if self.strategy not in STRATEGIES:
            raise ValueError(
                f"intervention.strategy={self.strategy!r} is unknown; allowed values: {STRATEGIES}"
            )
        for name in ("image_space", "state_space"):
            if getattr(self, name) not in SPACES:
                raise ValueError(
                    f"intervention.{name}={getattr(self, name)!r} is unknown; "
                    f"allowed values: {SPACES}"
                )
        if self.image_space == "centered":
            raise ValueError(
                "intervention.image_space='centered' is not a space for images (do(V) is a black "
                "image in [0, 1]: 'raw'); 'centered' applies to state_space only"
            )
        if not (self.noise_scale >= 0):
            raise ValueError(f"intervention.noise_scale={self.noise_scale!r} must be >= 0")


def intervene(x: Any, strategy: str, *, noise_scale: float = 0.5, seed: int = 0) -> Any:
    """Return the counterfactual value of ``x`` (batch first), same type, shape, dtype, device.

    Integer inputs (uint8 images) are supported for ``zero`` and ``mean``; ``gaussian`` needs a
    floating-point input.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy={strategy!r} is unknown; allowed values: {STRATEGIES}")
    if x.ndim < 1:
        raise ValueError(f"intervene needs a batch-first tensor, got shape {tuple(x.shape)}")
    if strategy == "zero":
        return x * 0 if is_torch(x) else np.zeros_like(x)
    return (
        _intervene_torch(x, strategy, noise_scale, seed)
        if is_torch(x)
        else _intervene_numpy(x, strategy, noise_scale, seed)
    )


def intervene_about(
    x: Any, center: Any, strategy: str, *, noise_scale: float = 0.5, seed: int = 0
) -> Any:
    """``intervene`` on ``x - center``, then ``center`` added back (``center``: one value per
    trailing dim, numpy or a list; None: about zero). ``zero`` gives ``center`` exactly."""
    if center is None:
        return intervene(x, strategy, noise_scale=noise_scale, seed=seed)
    if is_torch(x):
        import torch

        c = torch.as_tensor(np.asarray(center), dtype=x.dtype, device=x.device)
    else:
        c = np.asarray(center, dtype=x.dtype)
    if c.shape != tuple(x.shape[-1:]):
        raise ValueError(
            f"the state center has {tuple(c.shape)} values, the state {tuple(x.shape)}: the "
            "checkpoint's dataset statistics are not of this state"
        )
    if strategy == "zero":
        return c.expand_as(x).clone() if is_torch(x) else np.broadcast_to(c, x.shape).copy()
    return c + intervene(x - c, strategy, noise_scale=noise_scale, seed=seed)


def _intervene_numpy(x: np.ndarray, strategy: str, noise_scale: float, seed: int) -> np.ndarray:
    axes = tuple(range(1, x.ndim))
    xf = x.astype(np.float64)
    if strategy == "mean":
        mean = xf.mean(axis=axes, keepdims=True) if axes else xf
        if not np.issubdtype(x.dtype, np.floating):
            mean = np.rint(mean)
        return np.broadcast_to(mean, x.shape).astype(x.dtype)
    if not np.issubdtype(x.dtype, np.floating):
        raise ValueError(f"strategy 'gaussian' needs a floating-point input, got {x.dtype}")
    std = xf.std(axis=axes, keepdims=True) if axes else np.zeros_like(xf)
    noise = np.random.default_rng(seed).standard_normal(x.shape)
    return (xf + noise_scale * std * noise).astype(x.dtype)


def _intervene_torch(x: Any, strategy: str, noise_scale: float, seed: int) -> Any:
    import torch

    dims = tuple(range(1, x.ndim))
    xf = x.to(torch.float32) if not x.is_floating_point() else x
    if strategy == "mean":
        mean = xf.mean(dim=dims, keepdim=True) if dims else xf
        out = mean.expand_as(xf)
        return out.round().to(x.dtype) if not x.is_floating_point() else out.clone()
    if not x.is_floating_point():
        raise ValueError(f"strategy 'gaussian' needs a floating-point input, got {x.dtype}")
    std = xf.std(dim=dims, keepdim=True, correction=0) if dims else torch.zeros_like(xf)
    gen = torch.Generator(device=x.device).manual_seed(seed)
    noise = torch.randn(x.shape, generator=gen, device=x.device, dtype=x.dtype)
    return x + noise_scale * std * noise
