"""openpi's wire encoding: msgpack with numpy arrays as maps, as ``openpi_client.msgpack_numpy``.

An array is ``{b"__ndarray__": True, b"data": bytes, b"dtype": dtype.str, b"shape": shape}``, a
numpy scalar ``{b"__npgeneric__": True, b"data": value, b"dtype": dtype.str}``; object, void
and complex dtypes are refused. Written here because openpi-client pins numpy < 2, which cannot
share this environment; a test checks it against the real package where one is installed.
"""

from __future__ import annotations

from typing import Any

import msgpack
import numpy as np


def _pack(obj: Any) -> Any:
    if isinstance(obj, np.ndarray | np.generic) and obj.dtype.kind in ("V", "O", "c"):
        raise ValueError(f"unsupported dtype for openpi's protocol: {obj.dtype}")
    if isinstance(obj, np.ndarray):
        return {
            b"__ndarray__": True,
            b"data": np.ascontiguousarray(obj).tobytes(),
            b"dtype": obj.dtype.str,
            b"shape": obj.shape,
        }
    if isinstance(obj, np.generic):
        return {b"__npgeneric__": True, b"data": obj.item(), b"dtype": obj.dtype.str}
    return obj


def _unpack(obj: dict[Any, Any]) -> Any:
    if b"__ndarray__" in obj:
        arr = np.frombuffer(obj[b"data"], dtype=np.dtype(obj[b"dtype"]))
        return arr.reshape(tuple(obj[b"shape"])).copy()
    if b"__npgeneric__" in obj:
        return np.dtype(obj[b"dtype"]).type(obj[b"data"])
    return obj


def packb(obj: Any) -> bytes:
    return msgpack.packb(obj, default=_pack)


def unpackb(data: bytes) -> Any:
    return msgpack.unpackb(data, object_hook=_unpack)
