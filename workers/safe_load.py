"""Load torch-saved files without running pickled code.

``torch.load(weights_only=True)`` only rebuilds tensors and allow-listed types; here the
allow-list is numpy's array reconstruction, so a file that holds numpy arrays (LIBERO's
``.pruned_init`` init states, saved by ``torch.save`` of an ndarray) loads, and a file that
holds anything else (a pickle that would run code) is refused. Model weights never come
this way: they load from safetensors only (workers.backbones.lerobot.adapter).
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np


def _numpy_globals() -> list[object]:
    reconstruct = np._core.multiarray._reconstruct
    dtypes = [type(np.dtype(t)) for t in ("float64", "float32", "int64", "int32", "bool", "uint8")]
    # files written by numpy 1.x name the function numpy.core.multiarray._reconstruct
    return [
        (reconstruct, "numpy.core.multiarray._reconstruct"),
        (reconstruct, "numpy._core.multiarray._reconstruct"),
        np.ndarray,
        np.dtype,
        *dtypes,
    ]


def load_numpy_array(path: str | Path) -> np.ndarray:
    """A numpy array saved with ``torch.save``, loaded with ``weights_only=True``; raise
    ValueError for a file that holds anything else."""
    import torch

    try:
        with torch.serialization.safe_globals(_numpy_globals()):
            value = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as e:
        first = str(e).strip().splitlines()[-1][:300]
        raise ValueError(
            f"{path}: refused, it is not a plain array file (loading it would run pickled code): "
            f"{first}"
        ) from None
    if isinstance(value, torch.Tensor):
        value = value.numpy()
    if not isinstance(value, np.ndarray):
        raise ValueError(f"{path}: expected a numpy array, got {type(value).__name__}")
    return value
