"""A lerobot policy object already in memory (a training loop's) behind the harness's lerobot
backbone: :class:`LerobotBackbone`'s inference, interventions and noise, without loading from a
folder. Only the construction differs: the policy, its processors and its config are given
instead of read from ``config.json`` / ``model.safetensors``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from pipeline.errors import ConfigError
from workers.backbones.lerobot.adapter import LerobotBackbone
from workers.backbones.lerobot.checkpoint import register_project_policies


class PolicyBackbone(LerobotBackbone):
    """``policy`` (a lerobot ``PreTrainedPolicy``) as a backbone. The caller keeps the policy:
    it is put in eval mode for each call and given back in the mode it was in."""

    def __init__(
        self,
        policy: Any,
        preprocessor: Any = None,
        postprocessor: Any = None,
        device: str | None = None,
        camera_map: dict[str, str] | None = None,
        chunk_len: int | None = None,
    ) -> None:
        register_project_policies()
        cfg = policy.config
        params = list(policy.parameters())
        self.device = (
            torch.device(device) if device else params[0].device if params else torch.device("cpu")
        )
        if (preprocessor is None) != (postprocessor is None):
            raise ConfigError("give both preprocessor and postprocessor, or neither")
        if preprocessor is None:
            path = getattr(cfg, "pretrained_path", None)
            if path is None or not Path(path).is_dir():
                raise ConfigError(
                    f"the policy's processors: config.pretrained_path is {path!r}, not a folder to "
                    "load them from; pass preprocessor= and postprocessor= (the pipelines the "
                    "policy trains with, lerobot's make_pre_post_processors)"
                )
            from lerobot_policy_idr.processor_idr import load_base_processors

            preprocessor, postprocessor = load_base_processors(Path(path), str(self.device))
        self.path = str(getattr(cfg, "pretrained_path", "") or "<in memory>")
        self.config = cfg
        self.policy = policy
        try:
            self._adopt(preprocessor, postprocessor, camera_map, chunk_len)
        except ValueError as e:
            raise ConfigError(str(e).replace("backbone.params.", "")) from None

    def close(self) -> None:
        """Take the intervention hook off the caller's preprocessor (it stays theirs)."""
        if self._state_intervention_hook in self.pre.after_step_hooks:
            self.pre.unregister_after_step_hook(self._state_intervention_hook)

    def predict_chunk(self, obs: Any, noise: Any = None, intervention: Any = None) -> torch.Tensor:
        was_training = bool(self.policy.training)
        self.policy.eval()
        try:
            return super().predict_chunk(obs, noise=noise, intervention=intervention)
        finally:
            self.policy.train(was_training)
