"""FAKE plugin: fails at import, as one missing a dependency does."""

from lerobot_policy_fake_broken.configuration_fake_broken import FakeBrokenConfig

__all__ = ["FakeBrokenConfig"]
