"""The env server's wire format: arrays cross as raw buffers, exactly, and bad frames are refused."""

from __future__ import annotations

import socket
import struct

import msgpack
import numpy as np
import pytest

from workers.envs.server import wire


@pytest.mark.parametrize(
    "arr",
    [
        np.arange(200 * 200 * 3, dtype=np.uint8).reshape(200, 200, 3),
        np.linspace(-1, 1, 15, dtype=np.float32),
        np.array([[1.5, np.nan], [np.inf, -0.0]]),
        np.array(True),
        np.zeros((0, 7), dtype=np.float64),
        np.arange(12, dtype=">i4").reshape(3, 4)[:, ::2],  # big-endian, not contiguous
    ],
)
def test_arrays_round_trip_bit_exact_and_writable(arr):
    out = wire.decode(wire.encode({"a": arr}))["a"]
    assert out.dtype == arr.dtype and out.shape == arr.shape
    assert out.tobytes() == np.ascontiguousarray(arr).tobytes()
    out[...] = 0  # the receiver owns its array, as from an env in its own process


def test_an_image_is_carried_as_its_bytes_not_as_text():
    img = np.random.default_rng(0).integers(0, 256, (256, 256, 3), dtype=np.uint8)
    assert len(wire.encode(img)) < img.nbytes + 64


def test_nested_values_and_numpy_scalars():
    msg = {"status": {"steps": np.int64(3), "success": np.bool_(True), "ids": {2, 1}}, "x": None}
    assert wire.decode(wire.encode(msg)) == {
        "status": {"steps": 3, "success": True, "ids": [1, 2]},
        "x": None,
    }


def test_what_cannot_cross_is_refused_by_name():
    with pytest.raises(TypeError, match="object array"):
        wire.encode(np.array([object()]))
    with pytest.raises(TypeError, match="cannot send a complex"):
        wire.encode(1j)


def test_frames_over_a_socket_and_a_closed_peer():
    import threading

    a, b = socket.socketpair()
    big = np.ones((512, 512, 3), dtype=np.uint8)  # more than a socket buffer: sent as we read

    def sender() -> None:
        wire.send(a, {"op": "step", "image": big})
        wire.send(a, {"op": "small"})

    t = threading.Thread(target=sender)
    t.start()
    got = wire.recv(b)
    assert got["op"] == "step" and np.array_equal(got["image"], big)
    assert wire.recv(b) == {"op": "small"}
    t.join(timeout=10)
    a.close()
    with pytest.raises(wire.WireError, match="closed"):
        wire.recv(b)
    b.close()


def test_a_stream_that_is_not_this_protocol_is_refused():
    a, b = socket.socketpair()
    a.sendall(struct.pack("!I", wire.MAX_FRAME + 1))
    with pytest.raises(wire.WireError, match="not this protocol"):
        wire.recv(b)
    a.close()
    b.close()


@pytest.mark.parametrize(
    ("frame", "error"),
    [
        (struct.pack("!I", 1025), wire.FrameTooLarge),  # over the reader's bound of 1 KiB
        (struct.pack("!I", 16) + b"\xc1" * 16, wire.MalformedFrame),  # never valid msgpack
        (struct.pack("!I", 2) + b"\x01\x02", wire.MalformedFrame),  # a number, trailing bytes
        # an array whose header promises more bytes than it carries
        (lambda: _lying_array(), wire.MalformedFrame),
    ],
)
def test_a_bad_frame_is_one_wire_error_of_its_kind(frame, error):
    a, b = socket.socketpair()
    a.sendall(frame() if callable(frame) else frame)
    with pytest.raises(error):
        wire.recv(b, max_frame=1024)
    a.close()
    b.close()


def _lying_array() -> bytes:
    header = msgpack.packb(["<f8", [1000, 1000]])
    ext = msgpack.ExtType(1, struct.pack("!I", len(header)) + header + b"\x00" * 16)
    payload = msgpack.packb({"x": ext}, use_bin_type=True)
    return struct.pack("!I", len(payload)) + payload


def test_the_env_server_ends_quietly_on_what_is_not_a_request():
    """The env server's loop (shared frame rules): an undecodable frame, or one over its request
    bound, ends its loop without an exception (its process then exits); what came before was
    answered."""
    from workers.envs.server.serve import REQUEST_MAX_FRAME, serve

    for bad in (struct.pack("!I", 8) + b"\xc1" * 8, struct.pack("!I", REQUEST_MAX_FRAME + 1)):
        a, b = socket.socketpair()
        wire.send(a, {"op": "hello"})
        a.sendall(bad)
        serve(b)  # returns: no traceback, no reply to the bad frame
        assert wire.recv(a)["ok"] is True
        a.close()
        b.close()
