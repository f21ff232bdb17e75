"""The lerobot-specific parts of the test-time runtime, shared by the harness's episode loop
and the ``idr`` policy: temporal ensembling through lerobot's own ``ACTTemporalEnsembler``.

The model-free parts (which forwards a method needs, how they become a chunk) are in
``idr_core.methods``; this module holds what needs lerobot.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


class TemporalEnsemble:
    """lerobot's ``ACTTemporalEnsembler`` (ACT's test-time averaging: an exponentially weighted
    mean of the overlapping chunks' actions for the current step, weights ``exp(-coeff * i)``,
    i = 0 for the oldest chunk) on chunks of one episode, numpy or torch, batch first.

    Built at an episode's first inference (the chunk length is the base's), reset with it."""

    def __init__(self, coeff: float, chunk_len: int) -> None:
        from lerobot.policies.act.modeling_act import ACTTemporalEnsembler

        self.chunk_len = chunk_len
        self._ensembler = ACTTemporalEnsembler(coeff, chunk_len)
        self._ensembler.reset()

    def update(self, chunk: Any) -> Any:
        """The action to execute now, given the chunk inferred at this step: (B, T, D) ->
        (B, D), in ``chunk``'s array type."""
        as_numpy = isinstance(chunk, np.ndarray)
        x = torch.as_tensor(chunk)
        if x.ndim != 3 or x.shape[1] != self.chunk_len:
            raise ValueError(
                f"temporal ensembling takes (B, {self.chunk_len}, D) chunks, got {tuple(x.shape)}"
            )
        # lerobot's ensembler keeps float64 counts and the chunks' own dtype
        action = self._ensembler.update(x)
        return action.numpy() if as_numpy else action
