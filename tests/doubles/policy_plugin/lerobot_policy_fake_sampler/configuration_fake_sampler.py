"""FAKE: the config of a small stochastic policy, as a third party would write one."""

from __future__ import annotations

from dataclasses import dataclass

from lerobot.configs import PreTrainedConfig
from lerobot.configs.types import NormalizationMode
from lerobot.optim.optimizers import AdamWConfig


@PreTrainedConfig.register_subclass("fake_sampler")
@dataclass
class FakeSamplerConfig(PreTrainedConfig):
    chunk_size: int = 4
    n_action_steps: int = 4
    hidden: int = 16
    noise_std: float = 0.3  # sampled at inference with torch.randn; no noise argument
    normalization_mapping: dict[str, NormalizationMode] | None = None

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.normalization_mapping is None:
            self.normalization_mapping = {
                "VISUAL": NormalizationMode.MEAN_STD,
                "STATE": NormalizationMode.MEAN_STD,
                "ACTION": NormalizationMode.MEAN_STD,
            }

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(lr=1e-3)

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        if not self.image_features or self.robot_state_feature is None:
            raise ValueError("fake_sampler needs an image and a state")

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(self.chunk_size))

    @property
    def reward_delta_indices(self) -> None:
        return None
