"""A lerobot policy object already in memory (a training loop's) behind the harness's lerobot
backbone: :class:`LerobotBackbone`'s inference, interventions and noise, without loading from a
folder. Only the construction differs: the policy, its processors and its config are given
instead of read from ``config.json`` / ``model.safetensors``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from pipeline.errors import ConfigError
from workers.backbones.lerobot.adapter import (
    IMAGE_PREFIX,
    RESIZE_KEYS,
    STATE_KEY,
    LerobotBackbone,
    image_suffix,
    register_project_policies,
    split_postprocessor,
)


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
        from idr_core.sampling import crn_mode
        from lerobot_policy_idr.runtime import history_length

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
        self.pre = preprocessor
        self.post, self.finish_chunk = split_postprocessor(postprocessor)
        self.name = f"lerobot:{cfg.type}"
        image_keys = [k for k in cfg.input_features if image_suffix(k) is not None]
        self._image_key = {str(image_suffix(k)): k for k in image_keys}
        mapping = camera_map or {s: s for s in self._image_key}
        wanted = {self._image_key.get(v, IMAGE_PREFIX + v) for v in mapping.values()}
        if wanted != set(image_keys):
            raise ConfigError(
                f"camera_map={mapping} gives policy image keys {sorted(wanted)}, but the policy's "
                f"config declares {sorted(image_keys)}: map each frame camera to one of them"
            )
        self.camera_map = mapping
        self.cameras = tuple(mapping)
        self.image_shapes = {k: tuple(cfg.input_features[k].shape) for k in image_keys}
        self.resizes_images = any(getattr(cfg, k, None) for k in RESIZE_KEYS)
        state = cfg.input_features.get(STATE_KEY)
        self.state_dim = int(state.shape[0]) if state is not None else 0
        self.action_dim = int(cfg.output_features["action"].shape[0])
        self.chunk_len = int(
            chunk_len
            or getattr(cfg, "n_action_steps", None)
            or getattr(cfg, "chunk_size", None)
            or cfg.action_chunk_size
        )
        self.history_steps = history_length(cfg)
        self.crn_mode = crn_mode(cfg.type, policy.predict_action_chunk)
        self.can_batch = self.crn_mode != "seeded_rng"
        self._normalizer_index = self._find_normalizer()
        self._pending_do = None
        self.pre.register_after_step_hook(self._state_intervention_hook)

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
