"""An IDR folder loaded as lerobot's tools load it, for scripts with a control loop of their own."""

from __future__ import annotations

from pathlib import Path
from typing import Any


def load_idr(folder: str | Path, device: str | None = None) -> tuple[Any, Any, Any]:
    """``(policy, preprocessor, postprocessor)`` of an IDR folder (``lerobot-idr-wrap``), the
    device step set to ``device`` (default: the folder's). Per control step:
    ``post(policy.select_action(pre(observation)))``; ``policy.reset()`` between episodes."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    folder = Path(folder)
    cfg = PreTrainedConfig.from_pretrained(folder)
    cfg.pretrained_path = folder
    if device is not None:
        cfg.device = device
    policy = get_policy_class(cfg.type).from_pretrained(folder, config=cfg)
    overrides = {"device_processor": {"device": str(cfg.device)}}
    pre, post = make_pre_post_processors(
        cfg, pretrained_path=str(folder), preprocessor_overrides=overrides
    )
    return policy, pre, post
