"""The lerobot-specific parts of the test-time runtime, shared by the harness's episode loop
and the ``idr`` policy: temporal ensembling through lerobot's own ``ACTTemporalEnsembler``, a
step's noise drawn from its seed, a history-fed base's input, the dataset's state mean and
action bounds.

The model-free parts (which forwards a method needs, how they become a chunk) are in
``idr_core.methods``; this module holds what needs lerobot.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from idr_core.features import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE


class TemporalEnsemble:
    """lerobot's ``ACTTemporalEnsembler`` (ACT's test-time averaging: an exponentially weighted
    mean of the overlapping chunks' actions for the current step, weights ``exp(-coeff * i)``,
    i = 0 for the oldest chunk) on chunks of one episode, numpy or torch, batch first.

    Built at an episode's first inference (the chunk length is the base's), reset with it."""

    def __init__(self, coeff: float, chunk_len: int) -> None:
        from lerobot.policies.act.modeling_act import ACTTemporalEnsembler

        self.chunk_len = chunk_len
        self._ensembler = ACTTemporalEnsembler(coeff, chunk_len)
        self._ensembler.reset()

    def update(self, chunk: Any) -> Any:
        """The action to execute now, given the chunk inferred at this step: (B, T, D) ->
        (B, D), in ``chunk``'s array type."""
        as_numpy = isinstance(chunk, np.ndarray)
        x = torch.as_tensor(chunk)
        if x.ndim != 3 or x.shape[1] != self.chunk_len:
            raise ValueError(
                f"temporal ensembling takes (B, {self.chunk_len}, D) chunks, got {tuple(x.shape)}"
            )
        # lerobot's ensembler keeps float64 counts and the chunks' own dtype
        action = self._ensembler.update(x)
        return action.numpy() if as_numpy else action


def step_noise(
    config: Any, crn: str, batch_size: int, action_dim: int, seed: int, device: Any = None
) -> Any:
    """The noise of one forward of ``batch_size`` rows drawn from ``seed``, as idr-eval's
    lerobot backbone draws it from a step seed (and the idr policy, given that seed):
    ``shared_noise`` (``crn``, ``idr_core.sampling``): a standard normal of the base's noise
    shape from a generator seeded with it; ``seeded_rng``: the seed itself, one per row (the
    base's forward then runs under a torch RNG seeded with it); else None."""
    from idr_core.sampling import noise_shape

    if crn == "seeded_rng":
        return torch.tensor([seed] * batch_size)
    shape = noise_shape(config, batch_size, action_dim) if crn == "shared_noise" else None
    if shape is None:
        return None
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(shape, generator=gen).to(device or "cpu")


# -- observation history: what a history-fed base reads, for the harness and the plugin alike --

#: Base types whose ``predict_action_chunk`` reads the observation queues that their
#: ``select_action`` fills, not the batch it is given (VQ-BeT, Multi-Task DiT): IDR keeps the
#: frames and lends queues built from them to the base for each forward.
QUEUE_FED_TYPES = ("vqbet", "multi_task_dit")
#: Base types whose ``predict_action_chunk`` reads (rows, n_obs_steps, ...) observations
STACKED_TYPES = ("diffusion",)


def history_length(config: Any) -> int:
    """Frames one inference of a base of ``config`` reads: its ``n_obs_steps`` for a
    history-fed type (Diffusion, a queue-fed type), else 1 (the current frame alone)."""
    if config.type in STACKED_TYPES or config.type in QUEUE_FED_TYPES:
        return int(getattr(config, "n_obs_steps", 1) or 1)
    return 1


def stack_frames(frames: list[dict[str, Any]], n: int, keys: list[str]) -> dict[str, Any]:
    """Diffusion's input from the processed frames of an episode (oldest first, the current
    last): ``keys`` as (rows, n, ...) of the last ``n`` frames, the oldest repeated where the
    episode has fewer (as Diffusion's own queues start: filled with the first frame); the other
    entries from the current frame."""
    last = frames[-n:]
    last = [last[0]] * (n - len(last)) + last
    out = dict(frames[-1])
    for key in keys:
        out[key] = torch.stack([f[key] for f in last], dim=1)
    return out


def queue_frame(image_keys: list[str], batch: dict[str, Any]) -> dict[str, Any]:
    """One processed frame as a queue-fed base's ``select_action`` queues it: no action
    observed, its cameras stacked under ``observation.images``."""
    out = dict(batch)
    out.pop(ACTION, None)
    out[OBS_IMAGES] = torch.stack([batch[k] for k in image_keys], dim=-4)
    return out


def lent_queues(layout: dict[str, Any], frames: list[dict[str, Any]]) -> dict[str, Any]:
    """Queues of the base's ``layout`` (its ``_queues``: key -> deque with its maxlen) filled
    from the episode's queued frames (``queue_frame``, oldest first) by lerobot's own
    ``populate_queues``, as the base's ``select_action`` fills its queues step by step."""
    from collections import deque

    from lerobot.policies.utils import populate_queues

    queues = {k: deque(maxlen=q.maxlen) for k, q in layout.items()}
    for frame in frames:
        queues = populate_queues(queues, frame, exclude_keys=[ACTION])
    return queues


def base_input(
    config: Any, layout: dict[str, Any] | None, frames: list[dict[str, Any]]
) -> tuple[dict[str, Any], dict[str, Any] | None]:
    """What the base reads, from an episode's processed frames (oldest first, the current
    last), and the queues to lend it for the call (None: none): Diffusion's stacked frames
    (state, environment state and its image features); a queue-fed base's current frame and
    queues of its ``layout`` (its own ``_queues``) filled from the frames; any other base the
    current frame alone. The idr policy and idr-eval's lerobot adapter both build it here."""
    if config.type in QUEUE_FED_TYPES:
        queued = [queue_frame(list(config.image_features), f) for f in frames]
        return queued[-1], lent_queues(layout, queued)
    if config.type not in STACKED_TYPES:
        return frames[-1], None
    keys = [
        k
        for k in frames[-1]
        if k == OBS_STATE or k.startswith(OBS_ENV_STATE) or k in config.image_features
    ]
    return stack_frames(frames, history_length(config), keys), None


# -- do(S) centered: the base's dataset mean state ----------------------------------------------
def state_mean(steps: list[Any], dim: int | None = None) -> np.ndarray | None:
    """The mean of ``observation.state`` in the statistics of the first normalizer among a
    preprocessor's ``steps`` (float32, as that normalizer subtracts it); None where no
    normalizer holds one. Every normalization mode keeps the mean (lerobot computes all stats
    for every feature), so one definition serves MEAN_STD, MIN_MAX and IDENTITY bases alike.

    ``dim``: the state's own size. A base that pads its state to a larger size before its
    normalizer (lerobot pads at the end) holds statistics of the padded vector: its leading
    ``dim`` entries are the state's; statistics shorter than the state give None."""
    for step in steps:
        if type(step).__name__ != "NormalizerProcessorStep":
            continue
        tensors = getattr(step, "_tensor_stats", None) or {}
        mean = (tensors.get(OBS_STATE) or {}).get("mean")
        if mean is None:
            mean = ((getattr(step, "stats", None) or {}).get(OBS_STATE) or {}).get("mean")
        if mean is None:
            return None
        if isinstance(mean, torch.Tensor):
            mean = mean.detach().cpu().float().numpy()
        mean = np.asarray(mean, dtype=np.float32).reshape(-1)
        if dim is None:
            return mean
        return mean[:dim] if len(mean) >= dim else None
    return None


def action_bounds(steps: list[Any]) -> tuple[np.ndarray, np.ndarray] | None:
    """The dataset's action min and max (float32, physical units) in the statistics of the
    first action unnormalizer among a postprocessor's ``steps``; None without one or without
    both. A refined chunk is clipped into them (``idr_core.refiner.clip_into``)."""
    for step in steps:
        if type(step).__name__ != "UnnormalizerProcessorStep":
            continue
        stats = (getattr(step, "stats", None) or {}).get(ACTION) or {}
        if "min" not in stats or "max" not in stats:
            return None
        lo, hi = (
            np.asarray(
                v.detach().cpu().float().numpy() if isinstance(v, torch.Tensor) else v,
                dtype=np.float32,
            ).reshape(-1)
            for v in (stats["min"], stats["max"])
        )
        return lo, hi
    return None
