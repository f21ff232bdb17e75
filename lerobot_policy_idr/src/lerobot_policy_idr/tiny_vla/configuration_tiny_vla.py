"""Config of the tiny VLA, registered with lerobot as policy type ``tiny_vla``.

lerobot finds a policy's model class by rewriting the config's module path
``configuration_<type>`` to ``modeling_<type>``, hence the two module names.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lerobot.configs import NormalizationMode, PreTrainedConfig
from lerobot.configs.types import FeatureType
from lerobot.optim import AdamWConfig


@PreTrainedConfig.register_subclass("tiny_vla")
@dataclass
class TinyVLAConfig(PreTrainedConfig):
    """A CNN per camera (FiLM-conditioned on the instruction, spatial-softmax keypoints), a GRU
    over instruction tokens, the state, and an MLP head predicting a chunk of actions."""

    n_obs_steps: int = 1
    chunk_size: int = 8  # actions predicted per inference
    n_action_steps: int = 8  # actions executed from a chunk by select_action
    normalization_mapping: dict[str, NormalizationMode] = field(
        default_factory=lambda: {
            "VISUAL": NormalizationMode.IDENTITY,
            "STATE": NormalizationMode.MEAN_STD,
            "ACTION": NormalizationMode.MEAN_STD,
        }
    )
    vocab: list[str] = field(default_factory=list)  # instruction words; 0 = pad, 1 = unknown
    max_tokens: int = 24
    cnn_channels: tuple[int, ...] = (16, 32, 64)
    # one stride per conv layer; the keypoints come from the last map (96 px / 8 = 12 x 12 with
    # the default: a cell spans several centimetres of table)
    cnn_strides: tuple[int, ...] = (2, 2, 2)
    text_dim: int = 64
    hidden_dim: int = 256
    dropout: float = 0.1
    # state dims the net reads (None: all); the others are multiplied by 0 inside the model.
    # The tabletop state's end-effector orientation (dims 3-5) only moves by a few milliradians
    # with the commanded motion, which a net fed it learns to read as "the last action"
    ignored_state_dims: list[int] = field(default_factory=list)
    # square size (px) every camera image is resized to before its CNN, where it differs
    # (bilinear, antialiased); None: images are used as given. A checkpoint trained at 96 px
    # then runs where an env renders larger (lerobot's MetaWorld renders 480 px)
    resize_images_to: int | None = None
    optimizer_lr: float = 1e-3
    optimizer_weight_decay: float = 1e-4

    @property
    def observation_delta_indices(self) -> None:
        return None

    @property
    def action_delta_indices(self) -> list[int]:
        return list(range(self.chunk_size))

    @property
    def reward_delta_indices(self) -> None:
        return None

    def get_optimizer_preset(self) -> AdamWConfig:
        return AdamWConfig(lr=self.optimizer_lr, weight_decay=self.optimizer_weight_decay)

    def get_scheduler_preset(self) -> None:
        return None

    def validate_features(self) -> None:
        if not self.image_features:
            raise ValueError("tiny_vla needs at least one image feature (observation.images.*)")
        if self.robot_state_feature is None:
            raise ValueError("tiny_vla needs observation.state")
        if self.action_feature is None or self.action_feature.type is not FeatureType.ACTION:
            raise ValueError("tiny_vla needs an action output feature")
        if len(self.cnn_strides) != len(self.cnn_channels):
            raise ValueError(
                f"cnn_strides {list(self.cnn_strides)} needs one stride per layer of "
                f"cnn_channels {list(self.cnn_channels)}"
            )
        n_state = self.robot_state_feature.shape[0]
        bad = [d for d in self.ignored_state_dims if not 0 <= d < n_state]
        if bad:
            raise ValueError(f"ignored_state_dims {bad} outside the state's {n_state} dims")
        if self.resize_images_to is not None and self.resize_images_to < 8:
            raise ValueError(
                f"resize_images_to={self.resize_images_to}: give a size of at least 8 px (or "
                "null to use images as given)"
            )
        if self.n_action_steps > self.chunk_size:
            raise ValueError(f"n_action_steps={self.n_action_steps} > chunk_size={self.chunk_size}")
