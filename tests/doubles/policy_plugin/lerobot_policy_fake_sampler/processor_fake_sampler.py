"""FAKE: the plugin's processors, lerobot's default steps (lerobot finds this function by its
name, make_<type>_pre_post_processors, in the sibling processor_* module)."""

from __future__ import annotations

from typing import Any

from lerobot.processor import make_default_pre_post_processors

from lerobot_policy_fake_sampler.configuration_fake_sampler import FakeSamplerConfig


def make_fake_sampler_pre_post_processors(
    config: FakeSamplerConfig, dataset_stats: dict[str, Any] | None = None
) -> tuple[Any, Any]:
    return make_default_pre_post_processors(config, dataset_stats, normalizer_device=config.device)
