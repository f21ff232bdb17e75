"""The batched three-pass inference of IDR's infer stage, independent of any model or framework.

One forward runs the factual rows and the two counterfactual rows together: a batch of 3B
rows ordered ``[factual (B) | do(V) (B) | do(S) (B)]``, with the same noise for the three
thirds (common random numbers), so the action differences measure a modality's effect and not
sampling noise. The same packing serves every test-time method (``idr_core.methods``): a
request carries its method's passes, factual first. The harness's wrapper
(``workers.policy.wrapper``) and its policy service run every method through
:func:`infer_requests`; the lerobot policy type ``idr`` (``modeling_idr``), whose
counterfactual rows its preprocessor builds, splits its batch with :func:`split3`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from idr_core.methods import combine, passes
from idr_core.refiner import Diagnostics, RefinerConfig
from idr_core.tensors import is_torch


def repeat3(x: Any) -> Any:
    """``x`` stacked three times along the batch dim (torch or numpy): one noise draw shared
    by the factual and the two counterfactual thirds."""
    if is_torch(x):
        import torch

        return torch.cat([x, x, x], dim=0)
    return np.concatenate([x, x, x], axis=0)


def split3(x: Any, b: int) -> tuple[Any, Any, Any]:
    """The factual, do(V) and do(S) thirds of a 3B batch."""
    if x.shape[0] != 3 * b:
        raise ValueError(f"a three-pass batch has 3 x {b} rows, got {x.shape[0]}")
    return x[:b], x[b : 2 * b], x[2 * b :]


def three_passes(
    call: Callable[[Any, Any], Any],
    factual: Any,
    no_img: Any,
    no_prop: Any,
    noise: Any,
    *,
    b: int,
    batched: bool,
    concat: Callable[[list[Any]], Any],
) -> tuple[Any, Any, Any]:
    """The actions of the factual input and its two counterfactuals under one noise draw.

    ``call(inputs, noise)`` runs the model; ``concat`` stacks three inputs along the batch.
    ``batched``: one forward of 3B rows; else three calls of B rows with the same noise (for
    models that cannot take a batch, or whose noise comes from a seeded RNG per call).
    """
    if batched:
        out = call(concat([factual, no_img, no_prop]), None if noise is None else repeat3(noise))
        return split3(out, b)
    return call(factual, noise), call(no_img, noise), call(no_prop, noise)


@dataclass(frozen=True)
class PassRequest:
    """One request's inputs to an inference of a test-time method (``idr_core.methods``): the
    factual rows and the rows of the method's other passes (do(V) and do(S) for IDR), its
    noise (shared by its passes) and its settings. Settings travel with the request, never as
    state on a shared policy object."""

    factual: Any
    counterfactuals: tuple[Any, ...] | None  # the other passes' rows; None: the factual alone
    noise: Any
    cfg: RefinerConfig
    b: int  # rows of the factual input
    seed: int = 0  # the step seed: a placebo's direction (idr_core.refiner)
    # one noise per pass where the passes must not share it (ensemble's independent draws)
    noises: tuple[Any, ...] | None = None

    @property
    def parts(self) -> list[Any]:
        return [self.factual, *(self.counterfactuals or ())]

    def noise_of(self, i: int) -> Any:
        return self.noise if self.noises is None else self.noises[i]

    @property
    def rows(self) -> int:
        """Rows this request costs the base's forward."""
        return len(self.parts) * self.b


@dataclass(frozen=True)
class PassResult:
    """What one request's inference gave: the chunk to execute and what it was made from."""

    action: Any
    a_base: Any
    a_no_img: Any | None  # None where the method ran no do(V) pass
    a_no_prop: Any | None
    diag: Diagnostics | None
    rows: int = 0  # rows the request cost the base's forward


def infer_requests(
    call: Callable[[Any, Any], Any],
    requests: Sequence[PassRequest],
    *,
    concat: Callable[[list[Any]], Any],
    concat_noise: Callable[[list[Any]], Any],
    batched: bool,
) -> list[PassResult]:
    """The inference of each request's method: the one implementation that the harness's
    wrapper (one request) and its policy service (many) use.

    ``batched``: one forward over every request's rows, its passes' rows in order per request,
    each row with its own request's (and pass's) noise; else each pass of each request in turn
    with its noise. The outputs are split per request and turned into the executed chunk with
    the request's own settings (``idr_core.methods.combine``)."""
    if not batched:
        return [
            _answer(r, [call(part, r.noise_of(i)) for i, part in enumerate(r.parts)])
            for r in requests
        ]
    rows: list[Any] = []
    noises: list[Any] = []
    spans: list[tuple[int, int]] = []  # first row, rows
    first = 0
    for r in requests:
        parts = r.parts
        spans.append((first, len(parts) * r.b))
        first += len(parts) * r.b
        rows += parts
        noises += [r.noise_of(i) for i in range(len(parts)) if r.noise_of(i) is not None]
    if noises and len(noises) != len(rows):
        raise ValueError("requests packed into one forward either all carry noise or none does")
    out_all = call(concat(rows), concat_noise(noises) if noises else None)
    answers = []
    for r, (start, n) in zip(requests, spans, strict=True):
        a = out_all[start : start + n]
        answers.append(_answer(r, [a[i * r.b : (i + 1) * r.b] for i in range(len(r.parts))]))
    return answers


def _answer(r: PassRequest, outputs: list[Any]) -> PassResult:
    action, diag = combine(r.cfg, outputs, seed=r.seed)
    named = dict(zip(passes(r.cfg), outputs, strict=True))
    return PassResult(
        action, outputs[0], named.get("no_img"), named.get("no_prop"), diag, rows=r.rows
    )
