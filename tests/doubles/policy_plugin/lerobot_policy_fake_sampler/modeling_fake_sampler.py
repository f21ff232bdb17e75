"""FAKE: a policy that samples (torch.randn inside predict_action_chunk, no noise argument),
so a wrapper can share its noise across passes only by forking the RNG."""

from __future__ import annotations

from collections import deque
from typing import Any

import torch
from lerobot.policies.pretrained import PreTrainedPolicy
from torch import nn

from lerobot_policy_fake_sampler.configuration_fake_sampler import FakeSamplerConfig


class FakeSamplerPolicy(PreTrainedPolicy):
    config_class = FakeSamplerConfig
    name = "fake_sampler"

    def __init__(self, config: FakeSamplerConfig, **kwargs: Any) -> None:
        super().__init__(config)
        self.image_keys = sorted(config.image_features)
        state_dim = config.robot_state_feature.shape[0]
        self.action_dim = config.action_feature.shape[0]
        self.net = nn.Sequential(
            nn.Linear(3 * len(self.image_keys) + state_dim, config.hidden),
            nn.Tanh(),
            nn.Linear(config.hidden, config.chunk_size * self.action_dim),
        )
        self.reset()

    def get_optim_params(self) -> Any:
        return self.parameters()

    def reset(self) -> None:
        self._queue: deque[torch.Tensor] = deque(maxlen=self.config.n_action_steps)

    def forward(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict]:
        pred = self.predict_action_chunk(batch)
        return ((pred - batch["action"]) ** 2).mean(), {}

    @torch.no_grad()
    def predict_action_chunk(self, batch: dict[str, torch.Tensor], **kwargs: Any) -> torch.Tensor:
        pooled = [batch[k].mean(dim=(-2, -1)) for k in self.image_keys]  # (B, 3) per camera
        x = torch.cat([*pooled, batch["observation.state"]], dim=-1)
        mean = self.net(x).view(-1, self.config.chunk_size, self.action_dim)
        return mean + self.config.noise_std * torch.randn_like(mean)

    @torch.no_grad()
    def select_action(self, batch: dict[str, torch.Tensor], **kwargs: Any) -> torch.Tensor:
        if not self._queue:
            chunk = self.predict_action_chunk(batch)[:, : self.config.n_action_steps]
            self._queue.extend(chunk.transpose(0, 1))
        return self._queue.popleft()
