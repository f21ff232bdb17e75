"""IDR's two processor steps and the idr policy's pre/post-processors.

The policy only sees the preprocessed batch (normalized, maybe tokenized), so the
counterfactual inputs are made inside the base's own preprocessor, by two registered steps:

1. ``idr_counterfactual_batch`` right after the batch dimension is added (and after a
   relative-actions step, which must cache the factual state): the batch of B rows becomes
   ``[factual | do(V) | do(S)]`` of 3B rows; do(V) acts on raw [0, 1] images (a black image
   for every family); do(S) too when ``state_space`` is ``raw`` (about the origin) or
   ``centered`` (about the dataset mean the base's normalizer holds, kept in the step's
   config); the task strings are tripled.
2. ``idr_state_intervention`` right after the normalizer: do(S) on rows 2B:3B in normalized
   space (zero = the dataset mean), before any later step reads the state (pi0.5's state
   tokenizer turns it into text).

With ``refine_space=physical`` the base's action unnormalizer, and any step before it (those
act in the normalized space), move from the postprocessor into the policy (it refines physical
actions and returns them), so the folder's postprocessor is the base's steps after it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from idr_core.features import OBS_PREFIX, OBS_STATE, is_image_key
from idr_core.interventions import intervene, intervene_about
from idr_core.methods import method_of
from lerobot.configs.types import PipelineFeatureType, PolicyFeature
from lerobot.lerobot_types import TransitionKey
from lerobot.processor import (
    PolicyAction,
    PolicyProcessorPipeline,
    ProcessorStep,
    ProcessorStepRegistry,
)

BATCH_SIZE_KEY = "idr_batch_size"  # complementary data: B of the 3B rows
# after these (the last of them before the normalizer) the counterfactual rows are made
_BEFORE_COUNTERFACTUALS = ("AddBatchDimensionProcessorStep", "RelativeActionsProcessorStep")


def _rows(obs: dict[str, Any]) -> int:
    for key, value in obs.items():
        if isinstance(value, torch.Tensor) and (key == OBS_STATE or is_image_key(key)):
            return int(value.shape[0])
    raise ValueError(
        f"the idr policy needs {OBS_STATE!r} or an image tensor; observation has {sorted(obs)}"
    )


@ProcessorStepRegistry.register("idr_counterfactual_batch")
@dataclass
class IDRCounterfactualBatchStep(ProcessorStep):
    """B rows -> 3B rows ``[factual | do(V) | do(S)]`` (do(S) here only in raw space)."""

    strategy: str = "zero"
    state_space: str = "centered"
    noise_scale: float = 0.5
    seed: int = 0
    # what the base reads (from its config): checked on the first observation, before the
    # first chunk is computed and so before a robot moves
    expects: dict[str, list[int]] | None = None
    # do(S) under ``centered``: the base's dataset mean state (its normalizer's), physical units
    state_mean: list[float] | None = None

    def __post_init__(self) -> None:
        self._calls = 0

    def _check(self, obs: dict[str, Any]) -> None:
        for key, shape in (self.expects or {}).items():
            value = obs.get(key)
            if not isinstance(value, torch.Tensor):
                have = sorted(k for k in obs if k.startswith(OBS_PREFIX))
                raise ValueError(
                    f"the idr policy's base reads {key!r}, which the robot or env does not give "
                    f"(it gives {have}): map its names with --rename_map, or wrap a base trained "
                    "on this robot's features"
                )
            if key == OBS_STATE and int(value.shape[-1]) != shape[0]:
                raise ValueError(
                    f"{OBS_STATE}: the robot or env gives {int(value.shape[-1])} dims, the base "
                    f"reads {shape[0]}: wrap a base trained on this robot's state"
                )
            if is_image_key(key) and int(value.shape[-3]) != shape[0]:
                raise ValueError(
                    f"{key}: the robot or env gives {int(value.shape[-3])} channels, the base "
                    f"reads {shape[0]}"
                )

    def __call__(self, transition: dict) -> dict:
        obs = dict(transition[TransitionKey.OBSERVATION])
        if self._calls == 0:
            self._check(obs)
        b = _rows(obs)
        step_seed = self.seed + 7919 * self._calls  # gaussian interventions: new draw per call
        self._calls += 1
        images = sorted(k for k in obs if is_image_key(k))
        for key, value in list(obs.items()):
            if not isinstance(value, torch.Tensor) or value.ndim == 0 or value.shape[0] != b:
                continue
            no_img, no_prop = value, value
            if key in images:
                no_img = intervene(
                    value,
                    self.strategy,
                    noise_scale=self.noise_scale,
                    seed=step_seed + images.index(key),
                )
            if key == OBS_STATE and self.state_space in ("raw", "centered"):
                center = self.state_mean if self.state_space == "centered" else None
                no_prop = intervene_about(
                    value,
                    center,
                    self.strategy,
                    noise_scale=self.noise_scale,
                    seed=step_seed + 104729,
                )
            obs[key] = torch.cat([value, no_img, no_prop], dim=0)
        comp = dict(transition.get(TransitionKey.COMPLEMENTARY_DATA) or {})
        for key, value in list(comp.items()):
            if isinstance(value, list) and len(value) == b:
                comp[key] = value * 3
            elif isinstance(value, torch.Tensor) and value.ndim and value.shape[0] == b:
                comp[key] = torch.cat([value, value, value], dim=0)
        comp[BATCH_SIZE_KEY] = b
        out = dict(transition)
        out[TransitionKey.OBSERVATION] = obs
        out[TransitionKey.COMPLEMENTARY_DATA] = comp
        return out

    def reset(self) -> None:
        self._calls = 0

    def get_config(self) -> dict[str, Any]:
        return {
            "strategy": self.strategy,
            "state_space": self.state_space,
            "noise_scale": self.noise_scale,
            "seed": self.seed,
            "expects": self.expects,
            "state_mean": self.state_mean,
        }

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features  # rows are added, no feature changes


@ProcessorStepRegistry.register("idr_state_intervention")
@dataclass
class IDRStateInterventionStep(ProcessorStep):
    """do(S) on rows 2B:3B of the normalized state."""

    strategy: str = "zero"
    noise_scale: float = 0.5
    seed: int = 0

    def __call__(self, transition: dict) -> dict:
        comp = transition.get(TransitionKey.COMPLEMENTARY_DATA) or {}
        if BATCH_SIZE_KEY not in comp:
            raise ValueError(
                "idr_state_intervention found no idr_counterfactual_batch step before it: the "
                "idr preprocessor is damaged (remake the folder with lerobot-idr-wrap)"
            )
        obs = dict(transition[TransitionKey.OBSERVATION])
        b = int(comp[BATCH_SIZE_KEY])
        state = obs[OBS_STATE]
        cf = intervene(state[2 * b :], self.strategy, noise_scale=self.noise_scale, seed=self.seed)
        obs[OBS_STATE] = torch.cat([state[: 2 * b], cf], dim=0)
        out = dict(transition)
        out[TransitionKey.OBSERVATION] = obs
        return out

    def get_config(self) -> dict[str, Any]:
        return {"strategy": self.strategy, "noise_scale": self.noise_scale, "seed": self.seed}

    def transform_features(
        self, features: dict[PipelineFeatureType, dict[str, PolicyFeature]]
    ) -> dict[PipelineFeatureType, dict[str, PolicyFeature]]:
        return features


def _index(steps: list, name: str) -> int | None:
    for i, step in enumerate(steps):
        if type(step).__name__ == name:
            return i
    return None


def insert_idr_steps(
    pre: PolicyProcessorPipeline, post: PolicyProcessorPipeline, config: Any
) -> tuple[PolicyProcessorPipeline, PolicyProcessorPipeline]:
    """The base's pipelines with IDR's steps in place (``config``: an IDRConfig). A mode
    without counterfactual passes (``baseline``, ``ensemble``, ``temporal``) adds no step: the
    preprocessor is the base's."""
    steps = list(pre.steps)
    if any(type(s).__name__.startswith("IDR") for s in steps):
        raise ValueError("the preprocessor already holds IDR steps")
    post_steps = list(post.steps)
    if config.refine_space == "physical":
        i = _index(post_steps, "UnnormalizerProcessorStep")
        if i is not None:  # the policy runs these (normalized space) and unnormalizes, then refines
            post_steps = post_steps[i + 1 :]
    if "no_img" in method_of(config.mode).passes:
        norm = _index(steps, "NormalizerProcessorStep")
        anchors = [i for n in _BEFORE_COUNTERFACTUALS if (i := _index(steps, n)) is not None]
        anchors = [i for i in anchors if norm is None or i < norm]
        if not anchors:
            raise ValueError(
                "the base's preprocessor has no batch-dimension step before its normalizer: "
                f"{[type(s).__name__ for s in steps]}; cannot place IDR's counterfactual step"
            )
        where = max(anchors) + 1
        iv = config.intervention()
        expects = {
            k: list(f.shape)
            for k, f in (config.input_features or {}).items()
            if k == OBS_STATE or is_image_key(k)
        }
        mean = None
        if iv.state_space == "centered" and OBS_STATE in expects:
            from lerobot_policy_idr.runtime import state_mean

            found = state_mean(steps, int(expects[OBS_STATE][0]))
            if found is None:
                raise ValueError(
                    "policy.state_space='centered' but the base's preprocessor holds no dataset "
                    "mean of observation.state; use --policy.state_space=raw or normalized"
                )
            mean = [float(v) for v in found]
        steps.insert(
            where,
            IDRCounterfactualBatchStep(
                iv.strategy, iv.state_space, iv.noise_scale, iv.seed, expects or None, mean
            ),
        )
        if iv.state_space == "normalized":
            norm = _index(steps, "NormalizerProcessorStep")
            if norm is None:
                raise ValueError(
                    "policy.state_space='normalized' but the base's preprocessor has no "
                    "normalizer; use --policy.state_space=raw"
                )
            steps.insert(norm + 1, IDRStateInterventionStep(iv.strategy, iv.noise_scale, iv.seed))
    return _like(pre, steps), _like(post, post_steps)


def _like(pipe: PolicyProcessorPipeline, steps: list) -> PolicyProcessorPipeline:
    return PolicyProcessorPipeline(
        steps=steps, name=pipe.name, to_transition=pipe.to_transition, to_output=pipe.to_output
    )


def load_base_processors(
    base_path: Path, device: str | None
) -> tuple[PolicyProcessorPipeline, PolicyProcessorPipeline]:
    """The base checkpoint's saved pre/post-processors (device step set to ``device``)."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_pre_post_processors

    base_cfg = PreTrainedConfig.from_pretrained(base_path)
    overrides = {"device_processor": {"device": device}} if device else {}
    return make_pre_post_processors(
        base_cfg, pretrained_path=str(base_path), preprocessor_overrides=overrides
    )


def make_idr_pre_post_processors(
    config: Any, dataset_stats: dict | None = None
) -> tuple[
    PolicyProcessorPipeline[dict[str, Any], dict[str, Any]],
    PolicyProcessorPipeline[PolicyAction, PolicyAction],
]:
    """lerobot's factory hook for ``--policy.type=idr`` (no IDR folder): the base's saved
    processors with IDR's steps. ``dataset_stats`` is not used: the base's stats are."""
    pre, post = load_base_processors(config.resolve_base(), config.device)
    return insert_idr_steps(pre, post, config)
