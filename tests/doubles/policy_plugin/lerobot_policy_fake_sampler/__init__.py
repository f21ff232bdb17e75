"""FAKE third-party lerobot policy plugin: registers the policy type ``fake_sampler``."""

from lerobot_policy_fake_sampler.configuration_fake_sampler import FakeSamplerConfig

__all__ = ["FakeSamplerConfig"]
