"""From what an env renders to what a backbone reads (lerobot's convention)."""

from __future__ import annotations

import numpy as np
import torch

from workers.backbones.base import Observation
from workers.envs.base import EnvObservation


def image_to_tensor(img: np.ndarray) -> torch.Tensor:
    """uint8 (H, W, 3) -> float32 (1, 3, H, W) in [0, 1]."""
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).unsqueeze(0).float() / 255.0


def to_policy_observation(
    env_obs: EnvObservation, instruction: str, cameras: tuple[str, ...] | None = None
) -> Observation:
    """A batch of one: images as float (1, 3, H, W) in [0, 1], state as float32 (1, S).

    ``cameras``: the ones the backbone uses (None: all the env has); only those are rendered
    when the env renders lazily."""
    names = tuple(env_obs.images) if cameras is None else tuple(cameras)
    missing = [c for c in names if c not in env_obs.images]
    if missing:
        raise ValueError(
            f"the backbone uses cameras {missing} that the env does not render; env cameras: "
            f"{list(env_obs.images)} (set env.params.cameras, or backbone.params.camera_map)"
        )
    images = {cam: image_to_tensor(env_obs.images[cam]) for cam in names}
    state = torch.from_numpy(np.asarray(env_obs.state, dtype=np.float32)).unsqueeze(0)
    extras = {"privileged": [env_obs.privileged]} if env_obs.privileged is not None else {}
    return Observation(images=images, state=state, instruction=[instruction], extras=extras)
