"""What a backbone is to the pipeline: a frozen policy that predicts an action chunk.

A backbone sees a batch of :class:`Observation` (images by camera name, state, instruction
strings) and returns a chunk of actions of shape (B, chunk_len, action_dim). It may accept a
noise tensor (flow-matching and diffusion heads) so that the IDR wrapper can give the
factual and the two counterfactual passes the same noise (common random numbers).

Observation convention (lerobot's): images are float32 (B, 3, H, W) in [0, 1], state is
float32 (B, S), the instruction is a list of B strings. Arrays are torch tensors or numpy
arrays; a backbone converts what it gets.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Protocol, runtime_checkable

import numpy as np
from idr_core.tensors import is_torch


@dataclass
class Observation:
    """A batch of policy inputs."""

    images: dict[str, Any]  # camera name -> (B, 3, H, W) float in [0, 1]
    state: Any  # (B, S) float
    instruction: list[str]  # B strings
    # Rows on which the backbone itself must apply do(V) / do(S) (interventions in
    # `normalized` space, after its normalizer). None: nothing to apply.
    do_image: np.ndarray | None = None  # (B,) bool
    do_state: np.ndarray | None = None  # (B,) bool
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def batch_size(self) -> int:
        return len(self.instruction)

    def validate(self) -> None:
        """Raise ValueError when the fields disagree about the batch size."""
        b = self.batch_size
        if b == 0:
            raise ValueError("Observation.instruction is empty: a batch needs at least one row")
        if self.state.shape[0] != b:
            raise ValueError(f"Observation.state has batch {self.state.shape[0]}, instruction {b}")
        for cam, img in self.images.items():
            if img.ndim != 4 or img.shape[0] != b:
                raise ValueError(
                    f"Observation.images[{cam!r}] has shape {tuple(img.shape)}; expected (B={b}, C, H, W)"
                )


#: ``Observation.extras`` keys of a history-fed base's past frames (the episode loop fills
#: them): camera -> (B, k, 3, H, W) and (B, k, S), oldest first, the current frame excluded
HISTORY_IMAGES = "history_images"
HISTORY_STATE = "history_state"


def concat_observations(parts: list[Observation]) -> Observation:
    """Stack observations along the batch dim (torch or numpy, as given)."""
    first = parts[0]

    def cat(xs: list[Any]) -> Any:
        if is_torch(xs[0]):
            import torch

            return torch.cat(xs, dim=0)
        return np.concatenate(xs, axis=0)

    def flags(name: str) -> np.ndarray | None:
        values = [getattr(p, name) for p in parts]
        if all(v is None for v in values):
            return None
        return np.concatenate(
            [
                np.zeros(p.batch_size, bool) if v is None else v
                for p, v in zip(parts, values, strict=True)
            ]
        )

    def extra(k: str, v: Any) -> Any:
        if k == HISTORY_IMAGES:
            return {cam: cat([p.extras[k][cam] for p in parts]) for cam in v}
        if k == HISTORY_STATE:
            return cat([p.extras[k] for p in parts])
        # per-row extras (lists) are concatenated; others are taken from the first part
        if isinstance(v, list):
            return [x for p in parts for x in p.extras.get(k, [])]
        return v

    return Observation(
        images={cam: cat([p.images[cam] for p in parts]) for cam in first.images},
        state=cat([p.state for p in parts]),
        instruction=[s for p in parts for s in p.instruction],
        do_image=flags("do_image"),
        do_state=flags("do_state"),
        extras={k: extra(k, v) for k, v in first.extras.items()},
    )


# Members a backbone may have beyond the Backbone protocol, with the default the pipeline
# assumes when it has not (read them with backbone_member()).
OPTIONAL_BACKBONE_MEMBERS: dict[str, tuple[Any, str]] = {
    "cameras": (
        None,
        "tuple[str, ...]: the env cameras it reads (only those are rendered); None: all",
    ),
    "check_params": (
        None,
        "classmethod(params) raising ValueError: checks of its own before any actor starts "
        "(a checkpoint that does not exist or cannot fit the env); None: none",
    ),
    "dry_run": (
        None,
        "classmethod(params, env: workers.io_spec.EnvIO) -> None: one trial inference on an "
        "observation shaped like the env's (a served model), raising ValueError naming both "
        "sides when the answer does not fit the env; the pre-flight calls it; None: no trial",
    ),
    "finish_chunk": (
        None,
        "callable(chunk) -> chunk: steps applied to the chunk the env executes, after IDR has "
        "refined it (a lerobot postprocessor's steps after its unnormalizer: VLA-JEPA's "
        "gripper binarization); predict_chunk returns the chunk before them, the space where "
        "IDR measures and refines; None: none",
    ),
    "history_steps": (
        1,
        "int: frames one inference reads (Diffusion's n_obs_steps, VQ-BeT's queues): the "
        "episode loop sends the past ones with each request (extras HISTORY_IMAGES and "
        "HISTORY_STATE, taken at every env step); 1: the current frame alone",
    ),
    "action_bounds": (
        None,
        "(lo, hi), numpy (action_dim,) each: the min and max of its training data's actions in "
        "the space predict_chunk returns (a lerobot checkpoint's unnormalizer statistics): a "
        "refined chunk is clipped into them, widened to the base action (idr.clip_actions); "
        "None: not clipped",
    ),
    "state_mean": (
        None,
        "numpy (state_dim,): the mean state of the data it was trained on, in physical units "
        "(a lerobot checkpoint's normalizer statistics): do(S) under state_space=centered is "
        "taken about it; None: no dataset statistics (do(S) about zero)",
    ),
    "remote": (
        False,
        "bool: the model runs in another process (a policy server) whose numerics are its own: "
        "its forwards are not padded to executor.forward_rows, and runs record numerics=remote",
    ),
    "describe": (
        None,
        "classmethod(params) -> workers.io_spec.PolicyIO | None: the cameras, image shapes, "
        "state and action dims its checkpoint declares, read without loading weights (the "
        "pre-flight matches them against the env); None: no check",
    ),
}


def backbone_member(backbone: Any, name: str) -> Any:
    """An optional member of ``backbone`` (see OPTIONAL_BACKBONE_MEMBERS), or its default."""
    default, _ = OPTIONAL_BACKBONE_MEMBERS[name]
    return getattr(backbone, name, default)


@runtime_checkable
class Backbone(Protocol):
    """The interface every backbone implements (lerobot adapter, tiny VLA, fakes); it may
    also have the members of OPTIONAL_BACKBONE_MEMBERS."""

    name: str
    chunk_len: int  # T of the predicted (B, T, D) chunk
    action_dim: int  # D
    # Where this backbone can apply interventions itself ("normalized"); raw-space ones are
    # applied by the wrapper on the Observation for any backbone.
    native_intervention_spaces: ClassVar[frozenset[str]]
    can_batch: bool  # False: the wrapper runs the three passes as three calls

    def reset(self) -> None:
        """Forget any per-episode state (queues, observation history)."""

    def make_noise(self, batch_size: int, seed: int) -> Any | None:
        """Noise for one batch, reproducible from ``seed``; None for a deterministic head."""

    def predict_chunk(
        self, obs: Observation, noise: Any | None = None, intervention: Any | None = None
    ) -> Any:
        """Predict (B, chunk_len, action_dim) actions, as a float tensor or array.

        ``intervention`` (an InterventionConfig) is passed when ``obs.do_image`` / ``obs.do_state``
        mark rows on which the backbone applies do() in its normalized space.
        """
