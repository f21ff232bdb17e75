"""The batched three-pass inference of IDR's infer stage, independent of any model or framework.

One forward runs the factual rows and the two counterfactual rows together: a batch of 3B
rows ordered ``[factual (B) | do(V) (B) | do(S) (B)]``, with the same noise for the three
thirds (common random numbers), so the action differences measure a modality's effect and not
sampling noise. Both the harness's wrapper (``workers.idr_policy``) and the lerobot policy
type ``idr`` (``modeling_idr``) build and split batches with these helpers.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np


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
