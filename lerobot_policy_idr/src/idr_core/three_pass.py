"""The batched three-pass inference of IDR's infer stage, independent of any model or framework.

One forward runs the factual rows and the two counterfactual rows together: a batch of 3B
rows ordered ``[factual (B) | do(V) (B) | do(S) (B)]``, with the same noise for the three
thirds (common random numbers), so the action differences measure a modality's effect and not
sampling noise. The harness's wrapper (``workers.idr_wrapper``) and its policy service run IDR
through :func:`infer_requests`; the lerobot policy type ``idr`` (``modeling_idr``), whose
counterfactual rows its preprocessor builds, splits its batch with :func:`split3`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from idr_core.refiner import Diagnostics, RefinerConfig, refine


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch")


def repeat3(x: Any) -> Any:
    """``x`` stacked three times along the batch dim (torch or numpy): one noise draw shared
    by the factual and the two counterfactual thirds."""
    if _is_torch(x):
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
    """One request's inputs to an IDR inference: the factual rows, and (for a cell that needs
    them) the do(V) and do(S) rows, its noise (shared by its passes) and its refiner settings.
    Settings travel with the request, never as state on a shared policy object."""

    factual: Any
    counterfactuals: tuple[Any, Any] | None  # (do(V), do(S)); None: the factual pass only
    noise: Any
    cfg: RefinerConfig
    b: int  # rows of the factual input


@dataclass(frozen=True)
class PassResult:
    """What one request's inference gave: the chunk to execute and what it was made from."""

    action: Any
    a_base: Any
    a_no_img: Any | None  # None when only the factual pass ran
    a_no_prop: Any | None
    diag: Diagnostics | None


def infer_requests(
    call: Callable[[Any, Any], Any],
    requests: Sequence[PassRequest],
    *,
    concat: Callable[[list[Any]], Any],
    concat_noise: Callable[[list[Any]], Any],
    batched: bool,
) -> list[PassResult]:
    """IDR's infer, diagnose and refine for many requests: the one implementation that the
    harness's wrapper (one request) and its policy service (many) use.

    ``batched``: one forward over every request's rows, ``[factual | do(V) | do(S)]`` per
    request, each row with its own request's noise; else each request's passes in turn with
    its noise (:func:`three_passes`). The outputs are split per request and refined with the
    request's own settings."""
    if not batched:
        out = []
        for r in requests:
            if r.counterfactuals is None:
                out.append(_answer(r, call(r.factual, r.noise)))
            else:
                no_img, no_prop = r.counterfactuals
                thirds = three_passes(
                    call, r.factual, no_img, no_prop, r.noise, b=r.b, batched=False, concat=concat
                )
                out.append(_answer(r, *thirds))
        return out
    rows: list[Any] = []
    noises: list[Any] = []
    spans: list[tuple[int, int]] = []  # first row, rows
    first = 0
    for r in requests:
        parts = [r.factual] if r.counterfactuals is None else [r.factual, *r.counterfactuals]
        spans.append((first, len(parts) * r.b))
        first += len(parts) * r.b
        rows += parts
        if r.noise is not None:
            noises += [r.noise] * len(parts)
    if noises and len(noises) != len(rows):
        raise ValueError("requests packed into one forward either all carry noise or none does")
    out_all = call(concat(rows), concat_noise(noises) if noises else None)
    answers = []
    for r, (start, n) in zip(requests, spans, strict=True):
        a = out_all[start : start + n]
        answers.append(_answer(r, a) if r.counterfactuals is None else _answer(r, *split3(a, r.b)))
    return answers


def _answer(r: PassRequest, a_base: Any, a_no_img: Any = None, a_no_prop: Any = None) -> PassResult:
    if a_no_img is None:
        return PassResult(a_base, a_base, None, None, None)
    action, diag = refine(a_base, a_no_img, a_no_prop, r.cfg)
    return PassResult(action, a_base, a_no_img, a_no_prop, diag)
