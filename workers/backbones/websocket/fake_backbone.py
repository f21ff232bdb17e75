"""The fake openpi server's closed-form policy (``fake_server.act``) as a backbone in this
process (a fake, not learned): the same rows as the remote backbone sends, the same actions, so
a benchmark can serve one near-zero-compute model through every path (in process, our policy
service, vla-eval's server, openpi's server). Named in a config as
``workers.backbones.websocket.fake_backbone:ClosedFormBackbone``."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np

from workers.backbones.websocket.fake_server import act

# the remote backbone's key map for this policy (ours -> the server's)
KEY_MAP = {"image:agentview": "observation/image", "state": "observation/state", "prompt": "prompt"}


class ClosedFormBackbone:
    """Actions img_gain * mean(image) + state_gain * mean(state), a (chunk_len, action_dim)
    chunk per row; deterministic (noise_std 0), so no noise is made."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset()
    can_batch = True
    name = "closed_form"
    cameras = ("agentview",)
    key_map = KEY_MAP

    def __init__(
        self,
        chunk_len: int = 4,
        action_dim: int = 7,
        img_gain: float = 2.0,
        state_gain: float = 0.5,
    ) -> None:
        self.chunk_len, self.action_dim = chunk_len, action_dim
        self.gains = (img_gain, state_gain, 0.0, chunk_len, action_dim)

    def reset(self) -> None:
        pass

    def make_noise(self, batch_size: int, seed: int) -> None:
        return None

    def predict_chunk(self, obs: Any, noise: Any = None, intervention: Any = None) -> np.ndarray:
        from workers.backbones.websocket.client import WebsocketBackbone

        rows = [WebsocketBackbone._row(self, obs, i) for i in range(obs.batch_size)]  # type: ignore[arg-type]
        return np.stack([act(r, *self.gains) for r in rows])
