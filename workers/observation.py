"""From what an env renders to what a backbone reads (lerobot's convention)."""

from __future__ import annotations

import numpy as np
import torch

from workers.backbones.base import Observation
from workers.envs.base import EnvObservation


def to_policy_observation(env_obs: EnvObservation, instruction: str) -> Observation:
    """uint8 (H, W, 3) images -> float32 (1, 3, H, W) in [0, 1]; state -> float32 (1, S)."""
    images = {
        cam: torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).unsqueeze(0).float()
        / 255.0
        for cam, img in env_obs.images.items()
    }
    state = torch.from_numpy(np.asarray(env_obs.state, dtype=np.float32)).unsqueeze(0)
    return Observation(images=images, state=state, instruction=[instruction])
