"""The tiny VLA's processors, where lerobot's factory looks for them by name
(``configuration_tiny_vla`` -> ``processor_tiny_vla.make_tiny_vla_pre_post_processors``), so
``lerobot-train --policy.type=tiny_vla`` builds them: lerobot's default pair (rename, batch,
device, normalize; unnormalize, cpu), the same pipelines ``training/train_tiny_vla.py`` saves."""

from __future__ import annotations

from typing import Any

from lerobot.processor.factory import make_default_pre_post_processors


def make_tiny_vla_pre_post_processors(
    config: Any, dataset_stats: dict[str, dict[str, Any]] | None = None
) -> tuple[Any, Any]:
    return make_default_pre_post_processors(config, dataset_stats=dataset_stats)
