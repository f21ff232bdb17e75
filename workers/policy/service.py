"""One backbone for many episodes: IDR's three passes of many requests in one forward.

A request is one episode's inference: its observation (a batch of one), its step seed and its
IDR cell (config and intervention). :func:`infer_many` builds the rows of all requests (the
factual one, and for IDR cells the do(V) and do(S) ones, exactly as ``IDRWrapper.infer`` builds
them), runs the backbone once over all of them, each row with its own request's noise (drawn
from its own step seed: common random numbers per episode and inference, as in-actor), splits
the output and refines each request with its own config. So an episode's actions never depend
on which other episodes shared its forward (for a backbone whose rows do not interact, which
a policy network's do not, up to the floating-point order of a batched kernel).

:class:`PolicyWorker` holds the backbone (a plain class, testable without Ray); the Ray actor
around it (``workers.policy.actor``) batches requests as they arrive.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from itertools import groupby
from typing import Any

import numpy as np
from idr_core.interventions import InterventionConfig
from idr_core.refiner import Diagnostics, RefinerConfig

from workers.backbones.base import Observation, backbone_member
from workers.hardware import hardware_class, hardware_record
from workers.policy.forward_shape import (
    NumericsError,
    as_numpy,
    check_row_independence,
    fix_forward_shape,
    set_torch_threads,
)
from workers.policy.wrapper import IDRStep, IDRWrapper, step_of


@dataclass(frozen=True)
class InferRequest:
    """One episode's inference, as the simulator side sends it."""

    obs: Observation  # a batch of one, numpy arrays (images float (1, 3, H, W), state (1, S))
    step_seed: int
    idr: RefinerConfig
    intervention: InterventionConfig


def _native(iv: InterventionConfig) -> bool:
    """Whether the backbone applies part of ``iv`` itself (a forward of its own)."""
    return iv.image_space == "normalized" or iv.state_space == "normalized"


def _to_numpy(x: Any) -> Any:
    return None if x is None else as_numpy(x)


def to_numpy_step(step: IDRStep) -> IDRStep:
    """The step with numpy arrays only (what crosses back to the simulator side)."""
    diag = None
    if step.diag is not None:
        diag = Diagnostics(**step.diag.to_numpy())
    return dataclasses.replace(
        step,
        action=_to_numpy(step.action),
        a_base=_to_numpy(step.a_base),
        a_no_img=_to_numpy(step.a_no_img),
        a_no_prop=_to_numpy(step.a_no_prop),
        diag=diag,
    )


def infer_many(
    policy: IDRWrapper, requests: list[InferRequest], by_instruction: bool = False
) -> list[IDRStep]:
    """Every request answered; one backbone forward per group of requests that share how the
    backbone applies interventions (all of them, unless some use normalized-space ones), and
    with ``by_instruction`` their instruction too.

    ``by_instruction`` is what a fixed forward shape needs: a text encoder may shape its work
    by the batch's instructions (the tiny VLA packs its RNN's sequences by length, so a row's
    float order depends on its mates' instruction lengths), and an in-actor forward holds one
    instruction; forwards of one instruction each give every row the same float order."""
    if not policy.batched:  # a backbone that cannot batch: each request's passes in turn
        return [policy.infer(r.obs, r.step_seed, r.idr, r.intervention) for r in requests]

    def forward_group(pair: tuple[int, InferRequest]) -> tuple[str, str]:  # "": all together
        iv = pair[1].intervention
        text = "\n".join(pair[1].obs.instruction) if by_instruction else ""
        return (repr(iv) if _native(iv) else "", text)

    answers: dict[int, IDRStep] = {}
    indexed = sorted(enumerate(requests), key=forward_group)
    for _, group in groupby(indexed, key=forward_group):
        answers.update(_one_forward(policy, list(group)))
    return [answers[i] for i in range(len(requests))]


def _one_forward(policy: IDRWrapper, group: list[tuple[int, InferRequest]]) -> dict[int, IDRStep]:
    """One forward for ``group`` (requests of one native intervention, or of raw ones only),
    through the wrapper's one IDR inference with each request's own settings."""
    t0 = time.perf_counter()
    reqs = [policy.request(r.obs, r.step_seed, r.idr, r.intervention) for _, r in group]
    native = _native(group[0][1].intervention)
    results = policy.infer_requests(reqs, group[0][1].intervention if native else None)
    ms = (time.perf_counter() - t0) * 1e3
    return {
        i: step_of(res, ms, batched=req.counterfactuals is not None, crn=req.noise is not None)
        for (i, _), req, res in zip(group, reqs, results, strict=True)
    }


def is_out_of_memory(exc: BaseException) -> bool:
    """A forward that failed for lack of device memory (torch's OutOfMemoryError, CUDA's or
    another allocator's "out of memory" RuntimeError)."""
    if type(exc).__name__ == "OutOfMemoryError":
        return True
    return isinstance(exc, RuntimeError) and "out of memory" in str(exc).lower()


def _free_device_memory() -> None:
    import sys

    torch = sys.modules.get("torch")
    if torch is not None and torch.cuda.is_available():
        torch.cuda.empty_cache()


class PolicyWorker:
    """A backbone wrapped by IDR that answers many episodes' requests (no per-episode state:
    the backbone is called on whole chunks, never through a queue of its own).

    ``rows``: every forward has that many rows (``workers.policy.forward_shape``; a row's actions
    then do not depend on its batch mates, checked on the first request); "dynamic" or None: as
    many as the batch holds.

    A dynamic forward that runs out of device memory is split: the requests are halved and the
    halves retried, down to a single request; the largest number of requests that fit is
    remembered (``fit``), and later batches are cut to it before their forward. Only a request
    that fails alone becomes an error (its episode's row); its batch mates are answered. A
    fixed-shape forward is never split (that would change its shape): its requests fail with
    an error naming executor.forward_rows."""

    def __init__(
        self,
        kind: str,
        params: dict[str, Any],
        batched: bool | None = None,
        rows: int | str | None = None,
        threads: int | None = None,
    ) -> None:
        from workers.backbones.factory import make_backbone

        set_torch_threads(threads)
        self.backbone = make_backbone(kind, params)
        self.device = params.get("device")
        self.policy = IDRWrapper(self.backbone, batched=batched)
        self.numerics = fix_forward_shape(self.policy, rows, threads)
        self.rows = self.policy.backbone.rows if self.policy.backbone is not self.backbone else None
        self.refusal: NumericsError | None = None  # the backbone failed the row check
        self.checked = self.rows is None
        self.forwards = 0
        self.requests = 0
        self.fit: int | None = None  # requests per forward that fit in memory (None: any)
        self.splits = 0  # forwards split for lack of memory

    def describe(self) -> dict[str, Any]:
        return {
            "name": self.backbone.name,
            "cameras": backbone_member(self.backbone, "cameras"),
            "batched": self.policy.batched,
            # steps after the base's action unnormalizer (temporal ensembling runs them after
            # its averaging, in the episode loop: not possible across the service)
            "finishes_chunks": backbone_member(self.backbone, "finish_chunk") is not None,
            "history_steps": backbone_member(self.backbone, "history_steps"),
            "numerics": self.numerics,
            "hardware": hardware_class(hardware_record(self.device)),
        }

    def infer_many(self, requests: list[InferRequest]) -> list[IDRStep]:
        """Every request answered, or the first request's error raised."""
        answers = self.infer_each(requests)
        for a in answers:
            if isinstance(a, BaseException):
                raise a
        return answers  # type: ignore[return-value]

    def infer_each(self, requests: list[InferRequest]) -> list[IDRStep | BaseException]:
        """One answer per request, in order: its step, or the error of a forward it failed
        alone (out of memory on its own) or with all its batch mates (any other error)."""
        self.requests += len(requests)
        requests = [dataclasses.replace(r, obs=_as_torch(r.obs)) for r in requests]
        if not self.checked:
            self._check_rows(requests[0])
        if self.refusal is not None:
            return [self.refusal] * len(requests)
        size = self.fit or len(requests)
        out: list[IDRStep | BaseException] = []
        for k in range(0, len(requests), size):
            out += self._fitting(requests[k : k + size])
        return out

    def _check_rows(self, req: InferRequest) -> None:
        """The first request's factual row through the fixed-shape check (two forwards): a
        backbone whose rows interact answers every request with the refusal."""
        inner = self.policy.backbone.inner
        noise = inner.make_noise(req.obs.batch_size, req.step_seed)
        try:
            check_row_independence(inner, req.obs, noise, self.rows)
        except NumericsError as exc:
            self.refusal = exc
        except Exception as exc:
            if not is_out_of_memory(exc):
                raise
            self.refusal = self._too_big(exc)
        self.checked = True

    def _too_big(self, exc: BaseException) -> NumericsError:
        return NumericsError(
            f"a forward of executor.forward_rows={self.rows} rows does not fit in device memory "
            f"({exc}): set a smaller executor.forward_rows (or executor.max_batch)"
        )

    def _fitting(self, requests: list[InferRequest]) -> list[IDRStep | BaseException]:
        self.forwards += 1
        try:
            answers = [
                to_numpy_step(s)
                for s in infer_many(self.policy, requests, by_instruction=self.rows is not None)
            ]
        except Exception as exc:
            if not is_out_of_memory(exc):
                raise
            _free_device_memory()
            if self.rows is not None:  # halving would change the forward's shape
                return [self._too_big(exc)] * len(requests)
            if len(requests) == 1:
                return [exc]
            self.splits += 1
            half = (len(requests) + 1) // 2
            self.fit = min(self.fit or half, half)
            return self._fitting(requests[:half]) + self._fitting(requests[half:])
        return answers


def _as_torch(obs: Observation) -> Observation:
    """The observation as the actor's backbone gets it in-actor (torch float32 tensors)."""
    import torch

    def t(x: Any) -> Any:
        return torch.from_numpy(np.ascontiguousarray(x)) if isinstance(x, np.ndarray) else x

    def image(x: Any) -> Any:  # uint8 on the wire (a quarter of the bytes): [0, 1] floats
        return t(x).float() / 255.0 if isinstance(x, np.ndarray) and x.dtype == np.uint8 else t(x)

    return dataclasses.replace(
        obs, images={k: image(v) for k, v in obs.images.items()}, state=t(obs.state)
    )
