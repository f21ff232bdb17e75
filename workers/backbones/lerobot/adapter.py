"""Any lerobot ``PreTrainedPolicy`` checkpoint as a backbone, with its saved processors.

Loading: ``config.json`` names the policy type; the policy class comes from lerobot's registry
and its weights from ``model.safetensors`` (pickled weights are refused); the pre- and
post-processor pipelines come from ``policy_preprocessor.json`` / ``policy_postprocessor.json``.
A hub id works too where the machine reaches a hub or has it cached; here nothing downloads.

Inference calls ``predict_action_chunk`` directly (``select_action`` keeps action queues and,
for Diffusion, observation history, which three passes per step would corrupt).

Where the interventions happen (lerobot's conventions, see shared/notes/lerobot.md):
- do(V) on raw [0, 1] images before the preprocessor (the IDR wrapper does it): a black image
  for every family;
- do(S) by default after the normalizer (``state_space: normalized``: zero = the dataset mean),
  through an after-step hook on the preprocessor's normalizer step, so it happens before any
  later step (pi0.5's state tokenizer); ``raw`` zeroes the physical state before the pipeline.

Common random numbers: policies whose ``predict_action_chunk`` takes ``noise`` (pi0, pi0.5,
SmolVLA, Diffusion) get the same noise for the three thirds of one 3B forward; stochastic
policies without it (X-VLA, GR00T) run the three passes sequentially, each under a forked RNG
seeded identically; deterministic ones (ACT) need neither. ``crn_mode`` records which.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, ClassVar

import torch
from idr_core.features import ACTION, IMAGE_PREFIX, OBS_STATE, camera_of
from idr_core.interventions import intervene
from idr_core.sampling import crn_mode

from workers.backbones.base import HISTORY_IMAGES, HISTORY_STATE, Observation
from workers.backbones.lerobot.checkpoint import (
    RESIZE_KEYS,
    check_checkpoint,
    policy_io,
    register_project_policies,
)
from workers.io_spec import PolicyIO


def split_postprocessor(post: Any) -> tuple[Any, Any | None]:
    """``post`` as (its steps up to and including the action unnormalizer, the steps after it
    or None). IDR measures and refines physical actions, as the plugin's
    ``refine_space=physical`` does; a step after the unnormalizer that changes values
    (VLA-JEPA binarizes its gripper) then applies to the refined chunk the env executes, not
    to the three passes. Device moves after it are kept in the first part: they change no
    value."""
    from lerobot.processor import DeviceProcessorStep, PolicyProcessorPipeline

    names = [type(s).__name__ for s in post.steps]
    if "UnnormalizerProcessorStep" not in names:
        return post, None
    cut = names.index("UnnormalizerProcessorStep") + 1
    after = post.steps[cut:]
    if all(isinstance(s, DeviceProcessorStep) for s in after):
        return post, None

    def part(steps: list[Any], name: str) -> Any:
        return PolicyProcessorPipeline(
            steps=steps,
            name=name,
            to_transition=post.to_transition,
            to_output=post.to_output,
        )

    return part(post.steps[:cut], f"{post.name}_physical"), part(after, f"{post.name}_finish")


class LerobotBackbone:
    """A lerobot policy checkpoint behind the Backbone protocol."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset({"normalized"})

    @classmethod
    def check_params(cls, params: dict[str, Any]) -> None:
        if "path" not in params:
            raise ValueError(
                "backbone.params.path is required: a lerobot checkpoint folder or hub id"
            )
        check_checkpoint(str(params["path"]), bool(params.get("allow_download", False)))

    @classmethod
    def describe(cls, params: dict[str, Any]) -> PolicyIO | None:
        """The checkpoint's inputs and outputs from its config.json (no weights, no GPU);
        None for a hub id, which is not on this machine to read."""
        path = check_checkpoint(str(params["path"]), bool(params.get("allow_download", False)))
        return None if path is None else policy_io(path, params.get("chunk_len"))

    def __init__(
        self,
        path: str,
        device: str = "cpu",
        camera_map: dict[str, str] | None = None,
        chunk_len: int | None = None,
        allow_download: bool = False,
    ) -> None:
        """``camera_map``: env camera -> policy image key suffix (``observation.images.<suffix>``).
        A run fills it in on the driver from the env's cameras and the names checkpoints give
        them (``workers.io_spec``: LIBERO's ``image`` / ``image2`` ...); give it for a checkpoint
        whose names no convention covers. Default here: the same names.
        ``allow_download``: a hub id may be fetched (off by default: runs are offline)."""
        from lerobot.configs.policies import PreTrainedConfig
        from lerobot.policies.factory import get_policy_class, make_pre_post_processors

        register_project_policies()
        check_checkpoint(path, allow_download)
        self.path = path
        self.device = torch.device(device)
        cfg = PreTrainedConfig.from_pretrained(path)
        cfg.device = str(self.device)
        cfg.pretrained_path = Path(path)  # as lerobot's CLIs: EO1 builds its VLM from its config
        self.config = cfg
        self.policy = (
            get_policy_class(cfg.type).from_pretrained(path, config=cfg).to(self.device).eval()
        )
        # the device step runs where the policy runs, whatever device it was trained on (a
        # checkpoint saved on a GPU names cuda), as lerobot-eval overrides it
        overrides = {"device_processor": {"device": str(self.device)}}
        pre, post = make_pre_post_processors(
            cfg, pretrained_path=path, preprocessor_overrides=overrides
        )
        self._adopt(pre, post, camera_map, chunk_len)

    def _adopt(
        self, pre: Any, post: Any, camera_map: dict[str, str] | None, chunk_len: int | None
    ) -> None:
        """What the backbone reads of ``self.policy`` and ``self.config`` and the processors
        (loaded from a folder here, given by a caller with a policy in memory:
        ``pipeline.api``)."""
        cfg = self.config
        self.pre = pre
        self.post, self.finish_chunk = split_postprocessor(post)
        from lerobot_policy_idr.runtime import action_bounds

        # refined chunks are clipped into these (idr.clip_actions), as the idr policy clips
        self.action_bounds = action_bounds(self.post.steps)
        self.name = f"lerobot:{cfg.type}"
        image_keys = [k for k in cfg.input_features if camera_of(k) is not None]
        self._image_key = {str(camera_of(k)): k for k in image_keys}  # suffix -> policy key
        mapping = camera_map or {s: s for s in self._image_key}
        wanted = {self._image_key.get(v, IMAGE_PREFIX + v) for v in mapping.values()}
        if wanted != set(image_keys):
            raise ValueError(
                f"backbone.params.camera_map={mapping} gives policy image keys {sorted(wanted)}, "
                f"but the checkpoint's config.json declares {sorted(image_keys)}: map each env "
                "camera to one of them"
            )
        self.camera_map = mapping
        self.cameras = tuple(mapping)  # env cameras to render
        self.image_shapes = {k: tuple(cfg.input_features[k].shape) for k in image_keys}
        # a policy that resizes its images (RESIZE_KEYS) takes any size of its channel count
        self.resizes_images = any(getattr(cfg, k, None) for k in RESIZE_KEYS)
        state = cfg.input_features.get(OBS_STATE)
        self.state_dim = int(state.shape[0]) if state is not None else 0
        self.action_dim = int(cfg.output_features[ACTION].shape[0])
        self.chunk_len = int(
            chunk_len
            or getattr(cfg, "n_action_steps", None)
            or getattr(cfg, "chunk_size", None)
            or cfg.action_chunk_size  # VQ-BeT executes its whole chunk
        )
        from lerobot_policy_idr.runtime import history_length

        # frames one inference reads (Diffusion's n_obs_steps...): the episode loop sends the
        # past ones with each request
        self.history_steps = history_length(cfg)
        self.crn_mode = crn_mode(cfg.type, self.policy.predict_action_chunk)
        self.can_batch = (
            self.crn_mode != "seeded_rng"
        )  # one seed cannot give three thirds equal noise
        self._normalizer_index = self._find_normalizer()
        from lerobot_policy_idr.runtime import state_mean

        # do(S) under state_space=centered: about the dataset mean state, in physical units
        state_feature = cfg.input_features.get(OBS_STATE)
        self.state_mean = (
            state_mean(self.pre.steps, int(state_feature.shape[0])) if state_feature else None
        )
        self._pending_do: tuple[torch.Tensor, Any] | None = None
        self.pre.register_after_step_hook(self._state_intervention_hook)

    def _find_normalizer(self) -> int | None:
        for i, step in enumerate(self.pre.steps):
            if type(step).__name__ == "NormalizerProcessorStep":
                return i
        return None

    def _state_intervention_hook(self, index: int, transition: Any) -> None:
        """After the normalizer: do(S) on the flagged rows, in normalized space."""
        if self._pending_do is None or index != self._normalizer_index:
            return
        from lerobot.lerobot_types import TransitionKey

        rows, iv = self._pending_do
        obs = transition[TransitionKey.OBSERVATION]
        state = obs[OBS_STATE]
        cf = intervene(state, iv.strategy, noise_scale=iv.noise_scale, seed=iv.seed)
        obs[OBS_STATE] = torch.where(rows.to(state.device)[:, None], cf, state)

    # -- protocol ---------------------------------------------------------------------------
    def reset(self) -> None:
        self.policy.reset()

    def make_noise(self, batch_size: int, seed: int) -> Any:
        """The step's noise from its seed, drawn as the idr policy draws it from one
        (``runtime.step_noise``)."""
        from lerobot_policy_idr.runtime import step_noise

        return step_noise(
            self.config, self.crn_mode, batch_size, self.action_dim, seed, self.device
        )

    def _batch(self, obs: Observation) -> dict[str, Any]:
        batch: dict[str, Any] = {}
        for env_cam, key in self.camera_map.items():
            if env_cam not in obs.images:
                raise ValueError(
                    f"the policy needs camera {env_cam!r}; the observation has {list(obs.images)}"
                )
            img = torch.as_tensor(obs.images[env_cam]).float()
            policy_key = self._image_key[key]
            want = self.image_shapes[policy_key]
            got = tuple(img.shape[1:])
            if got != want and (not self.resizes_images or got[0] != want[0]):
                raise ValueError(
                    f"camera {env_cam!r} gives images {got}, policy key "
                    f"{policy_key!r} expects {want}: set env.params.image_size to match"
                )
            batch[policy_key] = img
        if self.state_dim:
            state = torch.as_tensor(obs.state).float()
            if state.shape[1] != self.state_dim:
                raise ValueError(
                    f"env state has {state.shape[1]} dims, policy {OBS_STATE!r} expects {self.state_dim}"
                )
            batch[OBS_STATE] = state
        batch["task"] = list(obs.instruction)
        return batch

    def _frames(self, obs: Observation, batch: dict[str, Any]) -> list[dict[str, Any]]:
        """The episode's frames that a history-fed base reads, oldest first, the current last:
        the past ones travel with the request (``Observation.extras``, ``HISTORY_IMAGES`` /
        ``HISTORY_STATE``: the service stays a pure function of each request), each made a
        batch as the current one is."""
        images = obs.extras.get(HISTORY_IMAGES)
        if not images:
            return [batch]
        state = obs.extras.get(HISTORY_STATE)
        k = next(iter(images.values())).shape[1]
        past = [
            self._batch(
                Observation(
                    {cam: x[:, i] for cam, x in images.items()},
                    state[:, i] if state is not None else obs.state,
                    list(obs.instruction),
                )
            )
            for i in range(k)
        ]
        return [*past, batch]

    @torch.inference_mode()
    def predict_chunk(
        self, obs: Observation, noise: Any = None, intervention: Any = None
    ) -> torch.Tensor:
        batch = self._batch(obs)
        if obs.do_image is not None and obs.do_image.any():
            raise ValueError(
                "image interventions apply in raw space (before the preprocessor) for lerobot policies"
            )
        if obs.do_state is not None and obs.do_state.any():
            if self._normalizer_index is None:
                raise ValueError(
                    f"{self.name}: no normalizer step in the preprocessor for state_space=normalized"
                )
            self._pending_do = (torch.as_tensor(obs.do_state), intervention)
        try:  # each frame through the preprocessor, do(S) on the flagged rows of every frame
            frames = [self.pre(f) for f in self._frames(obs, batch)]
        finally:
            self._pending_do = None
        from lerobot_policy_idr.runtime import base_input

        # what the base reads of the frames, as the idr policy builds it
        processed, lent = base_input(self.config, getattr(self.policy, "_queues", None), frames)
        from lerobot_policy_idr.modeling_idr import weights_version

        version = weights_version(self.policy)
        own = getattr(self.policy, "_queues", None)
        if lent is not None:
            self.policy._queues = lent
        try:
            if self.crn_mode == "shared_noise" and noise is not None:
                actions = self.policy.predict_action_chunk(processed, noise=noise)
            elif self.crn_mode == "seeded_rng" and noise is not None:
                devices = [self.device] if self.device.type == "cuda" else []
                with torch.random.fork_rng(devices=devices):
                    torch.manual_seed(int(noise[0]))
                    actions = self.policy.predict_action_chunk(processed)
            else:
                actions = self.policy.predict_action_chunk(processed)
        finally:
            if lent is not None:
                self.policy._queues = own
        if weights_version(self.policy) != version:
            raise ValueError(
                f"{self.name} changed its own weights during predict_action_chunk (test-time "
                "training?): the grid's cells must run one frozen network, and IDR's "
                "counterfactual rows would train it; turn the policy's adaptation off"
            )
        return self.post(actions)[:, : self.chunk_len]
