"""IDR around any backbone: infer (three passes), diagnose and refine, keeping the interface.

The wrapper builds one batch of 3B observations (factual, do(V), do(S)) and calls the backbone
once with the same noise for the three thirds (common random numbers), so that the action
differences measure the modality's effect and not sampling noise. Backbones that cannot batch
get three calls with the same noise instead (the sequential path); both give the same result.
Mode ``baseline`` runs one factual pass and no counterfactuals at all.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from idr_core.interventions import InterventionConfig, intervene, intervene_about
from idr_core.methods import passes, sample_seeds
from idr_core.refiner import Diagnostics, RefinerConfig, clip_into
from idr_core.three_pass import PassRequest, PassResult, infer_requests

from workers.backbones.base import (
    HISTORY_IMAGES,
    HISTORY_STATE,
    Backbone,
    Observation,
    backbone_member,
    concat_observations,
)
from workers.policy.forward_shape import cat_rows


@dataclass
class IDRStep:
    """What one inference produced: the chunk to execute and everything needed to analyse it."""

    action: Any  # (B, T, D) refined chunk (a_base in baseline / diagnose modes)
    a_base: Any
    a_no_img: Any | None  # None in baseline mode
    a_no_prop: Any | None
    diag: Diagnostics | None  # None in baseline mode
    inference_ms: float  # wall time of the backbone call(s) + refinement
    batched: bool  # whether the three passes were one 3B forward
    crn: bool  # whether the three passes shared one noise draw
    pass_rows: int = 0  # rows of the base's forward its passes cost (passes x batch)


#: spaces the wrapper applies itself, for any backbone (centered: about the base's
#: ``state_mean``, zero for a base without one)
WRAPPER_SPACES = frozenset({"raw", "centered"})


def check_intervention_spaces(backbone: Any, name: str, intervention: InterventionConfig) -> None:
    """Normalized-space interventions only where ``backbone`` (an instance or its class)
    applies them itself; raw-space and centered ones the wrapper applies for any backbone."""
    native = getattr(backbone, "native_intervention_spaces", frozenset())
    for field_name in ("image_space", "state_space"):
        space = getattr(intervention, field_name)
        if space not in WRAPPER_SPACES and space not in native:
            raise ValueError(
                f"intervention.{field_name}={space!r} is not supported by backbone {name!r} "
                f"(it applies interventions in {sorted(native) or 'no'} space itself); use 'raw'"
            )


class IDRWrapper:
    """A backbone wrapped by the IDR refiner; ``infer`` returns an :class:`IDRStep`.

    Each inference carries its own settings (``infer(obs, seed, cfg, intervention)``), as a
    request to the shared policy service does: one wrapper serves every cell of a run and no
    cell's settings are set on it. ``cfg`` and ``intervention`` given here are only what an
    inference without its own uses (benchmarks, tests)."""

    def __init__(
        self,
        backbone: Backbone,
        cfg: RefinerConfig | None = None,
        intervention: InterventionConfig | None = None,
        batched: bool | None = None,
    ) -> None:
        self.backbone = backbone
        self.cfg = cfg or RefinerConfig()
        self.intervention = intervention or InterventionConfig()
        self._check_spaces(self.intervention)
        can_batch = bool(getattr(backbone, "can_batch", False))
        if batched and not can_batch:
            raise ValueError(f"batched=True but backbone {backbone.name!r} cannot batch")
        self.batched = can_batch if batched is None else batched

    def _check_spaces(self, intervention: InterventionConfig) -> None:
        check_intervention_spaces(self.backbone, self.backbone.name, intervention)

    def reset(self) -> None:
        self.backbone.reset()

    # -- infer -------------------------------------------------------------------------
    def counterfactuals(
        self, obs: Observation, step_seed: int = 0, intervention: InterventionConfig | None = None
    ) -> tuple[Observation, Observation]:
        """The do(V) and do(S) versions of ``obs``: raw-space ones applied here, normalized-space
        ones marked for the backbone."""
        iv = intervention or self.intervention
        b = obs.batch_size
        flag = np.ones(b, dtype=bool)
        kw = {"noise_scale": iv.noise_scale}
        if iv.image_space == "raw":
            images = {
                cam: intervene(
                    obs.images[cam], iv.strategy, seed=iv.seed + 7919 * step_seed + i, **kw
                )
                for i, cam in enumerate(sorted(obs.images))
            }
            no_img = Observation(
                images, obs.state, list(obs.instruction), extras=_past(obs, iv, step_seed, "img")
            )
        else:
            no_img = Observation(
                dict(obs.images), obs.state, list(obs.instruction), do_image=flag, extras=obs.extras
            )
        if iv.state_space in WRAPPER_SPACES:
            center = self.state_center(iv)
            state = intervene_about(
                obs.state, center, iv.strategy, seed=iv.seed + 7919 * step_seed + 104729, **kw
            )
            no_prop = Observation(
                dict(obs.images),
                state,
                list(obs.instruction),
                extras=_past(obs, iv, step_seed, "state", center),
            )
        else:
            no_prop = Observation(
                dict(obs.images), obs.state, list(obs.instruction), do_state=flag, extras=obs.extras
            )
        return no_img, no_prop

    def state_center(self, iv: InterventionConfig) -> Any:
        """What do(S) is taken about: the base's dataset mean state under ``centered`` (None
        for a base without dataset statistics: zero), None (zero) under ``raw``."""
        if iv.state_space != "centered":
            return None
        return backbone_member(self.backbone, "state_mean")

    def request(
        self,
        obs: Observation,
        step_seed: int = 0,
        cfg: RefinerConfig | None = None,
        intervention: InterventionConfig | None = None,
    ) -> PassRequest:
        """One inference's inputs (the method's passes, noise, settings); ``cfg`` /
        ``intervention`` default to the wrapper's own."""
        obs.validate()
        cfg = cfg or self.cfg
        intervention = intervention or self.intervention
        if intervention is not self.intervention:
            self._check_spaces(intervention)
        b = obs.batch_size
        names = passes(cfg)
        factual = _without(obs, NO_OBJECTS_KEY)
        noise = self.backbone.make_noise(b, step_seed)
        noises = None
        if "sample" in names:  # independent draws: the first is the factual pass's
            seeds = sample_seeds(step_seed, len(names))
            noises = (noise, *(self.backbone.make_noise(b, s) for s in seeds[1:]))
        others: list[Observation] = []
        if "no_img" in names:
            others += self.counterfactuals(factual, step_seed, intervention)
            if "no_prop" not in names:
                others.pop()
        if "no_objects" in names:
            others.append(objects_hidden(obs))
        others += [factual] * names.count("sample")
        return PassRequest(
            factual, tuple(others) or None, noise, cfg, b, seed=step_seed, noises=noises
        )

    def forward(self, intervention: InterventionConfig) -> Any:
        """The backbone call for rows of ``intervention``'s cells: (rows, noise) -> actions."""

        def call(obs: Observation, noise: Any) -> Any:
            native = obs.do_image is not None or obs.do_state is not None
            return self.backbone.predict_chunk(
                obs, noise=noise, intervention=intervention if native else None
            )

        return call

    def infer_requests(
        self, requests: list[PassRequest], intervention: InterventionConfig | None = None
    ) -> list[PassResult]:
        """Several requests of one intervention through ``idr_core``'s one IDR inference (one
        forward when the backbone batches)."""
        needs = any(r.counterfactuals is not None for r in requests)
        temporal = [r.cfg.mode == "temporal" for r in requests]
        results = infer_requests(
            self.forward(intervention or self.intervention),
            requests,
            concat=concat_observations,
            concat_noise=cat_rows,
            # one request of the factual pass alone is one call either way
            batched=self.batched and (needs or len(requests) > 1),
        )
        results = self._clipped(requests, results)
        finish = backbone_member(self.backbone, "finish_chunk")
        if finish is None:
            return results
        # temporal ensembling: the finishing steps run after the averaging (the actor's)
        return [
            r if t else replace(r, action=finish(r.action))
            for r, t in zip(results, temporal, strict=True)
        ]

    def _clipped(self, requests: list[PassRequest], results: list[PassResult]) -> list[PassResult]:
        """Refined chunks clipped into the base's action bounds (``clip_into``: the dataset's
        min/max widened to the base action), as the idr policy clips them; a base without
        bounds, a mode that executes a_base, or ``clip_actions: false`` are left as they are."""
        bounds = backbone_member(self.backbone, "action_bounds")
        if bounds is None:
            return results
        return [
            replace(r, action=clip_into(r.action, r.a_base, *bounds)[0])
            if q.cfg.refines and q.cfg.clip_actions
            else r
            for q, r in zip(requests, results, strict=True)
        ]

    def finish(self, action: Any) -> Any:
        """The base's steps after its action unnormalizer, on an executed chunk (identity where
        it has none)."""
        finish = backbone_member(self.backbone, "finish_chunk")
        return action if finish is None else finish(action)

    def infer(
        self,
        obs: Observation,
        step_seed: int = 0,
        cfg: RefinerConfig | None = None,
        intervention: InterventionConfig | None = None,
    ) -> IDRStep:
        """One inference: the factual pass (+ the two counterfactual passes) and refinement.

        ``step_seed`` makes the noise (and gaussian interventions) reproducible per step; the
        three passes always share one noise draw."""
        t0 = time.perf_counter()
        req = self.request(obs, step_seed, cfg, intervention)
        (res,) = self.infer_requests([req], intervention)
        ms = (time.perf_counter() - t0) * 1e3
        three = req.counterfactuals is not None
        return step_of(res, ms, batched=self.batched and three, crn=req.noise is not None)


#: ``Observation.extras`` key of the object-hidden renders (camera -> (B, 3, H, W)), which the
#: episode loop adds for a method with a ``no_objects`` pass (``pcd``)
NO_OBJECTS_KEY = "no_objects_images"


def _past(
    obs: Observation, iv: InterventionConfig, step_seed: int, what: str, center: Any = None
) -> dict[str, Any]:
    """``obs.extras`` with a raw-space intervention on its past frames too (a history-fed
    base's counterfactual rows see the intervened modality at every frame they read, as the
    idr policy's rows do), each frame seeded apart."""
    extras = dict(obs.extras)
    kw = {"noise_scale": iv.noise_scale}
    if what == "img" and HISTORY_IMAGES in extras:
        extras[HISTORY_IMAGES] = {
            cam: _per_frame(x, iv.strategy, iv.seed + 7919 * step_seed + 31 * i, kw)
            for i, (cam, x) in enumerate(sorted(extras[HISTORY_IMAGES].items()))
        }
    if what == "state" and HISTORY_STATE in extras:
        extras[HISTORY_STATE] = _per_frame(
            extras[HISTORY_STATE], iv.strategy, iv.seed + 7919 * step_seed + 104723, kw, center
        )
    return extras


def _per_frame(x: Any, strategy: str, seed: int, kw: dict[str, Any], center: Any = None) -> Any:
    """``intervene`` (about ``center``, for states) on each frame of (B, k, ...) as on a batch
    of B * k."""
    flat = x.reshape(x.shape[0] * x.shape[1], *x.shape[2:])
    return intervene_about(flat, center, strategy, seed=seed, **kw).reshape(x.shape)


def _without(obs: Observation, key: str) -> Observation:
    if key not in obs.extras:
        return obs
    extras = {k: v for k, v in obs.extras.items() if k != key}
    return replace(obs, extras=extras)


def objects_hidden(obs: Observation) -> Observation:
    """``obs`` with its images rendered with the task's objects hidden (``pcd``'s pass)."""
    hidden = obs.extras.get(NO_OBJECTS_KEY)
    if hidden is None:
        raise ValueError(
            "this mode contrasts against object-hidden renders, but the observation carries "
            f"none (extras[{NO_OBJECTS_KEY!r}]): the env must render them"
        )
    images = {cam: hidden[cam] for cam in obs.images}
    return replace(_without(obs, NO_OBJECTS_KEY), images=images)


def step_of(res: PassResult, ms: float, batched: bool, crn: bool) -> IDRStep:
    return IDRStep(
        res.action, res.a_base, res.a_no_img, res.a_no_prop, res.diag, ms, batched, crn, res.rows
    )
