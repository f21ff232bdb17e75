"""The wire format of the env servers and of the policy actors' sockets
(``workers.policy.socket_server``): length-prefixed msgpack frames, numpy arrays as raw buffers.

Both ends import this module: the actor (Python 3.12) and the env server (any Python >= 3.10
with numpy and msgpack, e.g. 3.11 for PyBullet or SAPIEN), so it needs nothing else. A frame
is a 4-byte big-endian length and a msgpack map. An ndarray travels as msgpack extension type
1 whose payload is a small msgpack header (dtype string, shape) and the array's bytes, so an
image is never text-encoded or pickled. (msgpack-numpy would do it as a map with the bytes
copied twice; its last release is from 2022, so the 20 lines are ours.)

Requests are ``{"op": name, ...}``; replies ``{"ok": True, "result": ...}`` or ``{"ok": False,
"type": exception class name, "message": ..., "traceback": ...}``.

Frame rules, the same for every reader (the env server, its client, the policy socket): a frame
longer than the reader's bound (``max_frame``; at most :data:`MAX_FRAME`) is refused on its
length prefix (:class:`FrameTooLarge`); a frame's bytes are read as they arrive, so a length
prefix alone allocates at most :data:`EAGER_BYTES` (a peer that announces a large frame and
sends nothing costs that much, not the announced size); a payload that does not decode is
:class:`MalformedFrame`. All three are :class:`WireError`: the reader closes the connection.
"""

from __future__ import annotations

import socket
import struct
from typing import Any

import msgpack
import numpy as np

PROTOCOL_VERSION = 1
MAX_FRAME = 1 << 30  # 1 GiB: a longer length prefix means a corrupt stream, not a message
# a frame up to this size is read into one buffer allocated from its length prefix; a longer
# one grows as its bytes arrive, by at most CHUNK_BYTES per read
EAGER_BYTES = 1 << 16
CHUNK_BYTES = 1 << 20
_NDARRAY = 1
_LEN = struct.Struct("!I")


class WireError(ConnectionError):
    """The peer closed the connection or sent something that is not a frame."""


class FrameTooLarge(WireError):
    """A length prefix above the reader's bound (refused before any of the payload is read)."""


class MalformedFrame(WireError):
    """A payload that is not a msgpack message of this protocol (undecodable, trailing bytes,
    an array whose header and bytes disagree)."""


def _default(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            raise TypeError("an object array cannot cross a socket (env server or policy actor)")
        arr = obj if obj.flags.c_contiguous else np.ascontiguousarray(obj)  # keeps 0-d
        header = msgpack.packb([arr.dtype.str, list(arr.shape)])
        return msgpack.ExtType(_NDARRAY, _LEN.pack(len(header)) + header + arr.tobytes())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, set | frozenset):
        return sorted(obj)
    raise TypeError(
        f"cannot send a {type(obj).__name__} over a socket (env server or policy actor)"
    )


def _ext_hook(code: int, data: bytes) -> Any:
    if code != _NDARRAY:
        return msgpack.ExtType(code, data)
    (n,) = _LEN.unpack_from(data)
    dtype, shape = msgpack.unpackb(data[_LEN.size : _LEN.size + n])
    # a copy: the receiver owns a writable array, as from an env in its own process
    return (
        np.frombuffer(data, dtype=np.dtype(dtype), offset=_LEN.size + n)
        .reshape(tuple(shape))
        .copy()
    )


def encode(message: Any) -> bytes:
    return msgpack.packb(message, default=_default, use_bin_type=True)


def decode(payload: bytes | bytearray | memoryview) -> Any:
    return msgpack.unpackb(payload, ext_hook=_ext_hook, raw=False, strict_map_key=False)


def send(sock: socket.socket, message: Any) -> None:
    payload = encode(message)
    if len(payload) < 65536:
        sock.sendall(_LEN.pack(len(payload)) + payload)
    else:  # large frames (images): the header apart, no concatenated copy
        sock.sendall(_LEN.pack(len(payload)))
        sock.sendall(payload)


def recv_exact(sock: socket.socket, n: int) -> bytearray:
    """``n`` bytes from ``sock``. Up to :data:`EAGER_BYTES` are read into one buffer; beyond,
    the buffer grows with what arrives (never allocated from ``n`` alone), so memory follows
    the bytes the peer really sent."""
    if n <= EAGER_BYTES:
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        while got < n:
            k = sock.recv_into(view[got:], n - got)
            if k == 0:
                raise WireError("the peer closed the connection")
            got += k
        return buf
    buf = bytearray()
    while len(buf) < n:
        chunk = sock.recv(min(n - len(buf), CHUNK_BYTES))
        if not chunk:
            raise WireError("the peer closed the connection")
        buf += chunk
    return buf


def recv(sock: socket.socket, max_frame: int = MAX_FRAME) -> Any:
    """The next message: its length prefix checked against ``max_frame`` before any of its
    payload is read, the payload read as it arrives, then decoded (see the frame rules)."""
    (n,) = _LEN.unpack(recv_exact(sock, _LEN.size))
    bound = min(max_frame, MAX_FRAME)
    if n > bound:
        raise FrameTooLarge(f"frame of {n} bytes announced, more than {bound}: not this protocol")
    payload = recv_exact(sock, n)
    try:
        return decode(payload)
    except WireError:
        raise
    except Exception as exc:  # msgpack's own errors, or an array header that lies
        raise MalformedFrame(
            f"a frame of {n} bytes that is not a message ({type(exc).__name__})"
        ) from None
