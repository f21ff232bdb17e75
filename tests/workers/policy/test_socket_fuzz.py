"""The policy socket fuzzed (hypothesis): truncated frames, wrong lengths, random bytes, valid
msgpack of the wrong shape, requests without the token or with a wrong one. The server
answers each with a refusal or closes the connection, nothing escapes its threads, its memory
grows by less than what its limits allow at once (a frame bound per authenticated connection),
and a real client talking beside the fuzzer all along gets
exactly the answers it gets alone. The server is the real policy actor body (its batcher, a
fixed forward shape) around the fake policy, without Ray; loopback only."""

from __future__ import annotations

import multiprocessing as mp
import socket
import struct
import threading
import time
from typing import Any

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from idr_core.refiner import RefinerConfig

from workers.envs.fakes import FakeMarkerEnv
from workers.envs.server import wire
from workers.episode.observation import to_policy_observation
from workers.io_spec import EnvIO
from workers.policy.actor import BatchingPolicyActor, PolicyServiceClient
from workers.policy.socket_client import PolicySocketConnection
from workers.policy.socket_messages import request_message
from workers.policy.socket_settings import (
    AUTH_FRAME_BYTES,
    RAY_CALLS,
    SocketLimits,
    SocketSettings,
    SocketToken,
    frame_bound,
)

PARAMS = {"chunk_len": 4, "gain": 5.0, "noise_std": 0.2}
FAKE_IO = EnvIO(cameras=("agentview",), image_size=32, state_dim=2, action_dim=2)
MAX_FRAME = frame_bound(FAKE_IO)
EPISODES = 4  # the real client's observations, cycled


def _requests():
    out = []
    for e in range(EPISODES):
        o = FakeMarkerEnv().reset("reach", e, 0)
        client = PolicyServiceClient(None, RAY_CALLS, cfg=RefinerConfig(mode="E"))
        out.append(client.request(to_policy_observation(o, o.status.instruction), 100 + e))
    return out


def _proc(pid: int, field: str) -> int:
    """A number of /proc/<pid>/status (VmRSS in kB, Threads)."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(field + ":"):
                return int(line.split()[1])
    raise KeyError(field)


def _rss_bytes(pid: int) -> int:
    return _proc(pid, "VmRSS") * 1024


def serve_in_child(pipe: Any, limits: SocketLimits) -> None:
    """The server's process (its memory and threads are measured alone): the policy actor's body
    with its socket; answers ``report`` with what escaped its threads and its counts."""
    escaped: list[str] = []
    threading.excepthook = lambda args: escaped.append(repr(args.exc_value))
    token = SocketToken.new()
    actor = BatchingPolicyActor(
        "fake_marker", PARAMS, None, 4, 1.0, rows=12, threads=1,
        socket_settings=SocketSettings("127.0.0.1", token, limits),
    )  # fmt: skip
    pipe.send((actor.endpoint().address, token.hex()))
    while (cmd := pipe.recv()) != "stop":
        assert cmd == "report"
        socket_stats = actor._socket.stats()
        pipe.send({"escaped": escaped, "socket": socket_stats, **actor.stats()})


class _RealClient(threading.Thread):
    """Sends the episodes' requests in turn for as long as the fuzzer runs, each compared with
    its answer alone; any difference or error is kept."""

    def __init__(self, address, token, want) -> None:
        super().__init__(daemon=True)
        self.address, self.token, self.want = address, token, want
        self.stop = threading.Event()
        self.answered = 0
        self.problems: list[str] = []

    def run(self) -> None:
        conn = PolicySocketConnection(self.address, self.token, MAX_FRAME)
        reqs = _requests()
        try:
            while not self.stop.is_set():
                i = self.answered % EPISODES
                got = conn.infer(reqs[i], "real:0")
                for name in ("action", "a_base", "a_no_img", "a_no_prop"):
                    if not np.array_equal(getattr(got, name), getattr(self.want[i], name)):
                        self.problems.append(f"request {i}: {name} differs")
                self.answered += 1
        except Exception as exc:
            self.problems.append(f"{type(exc).__name__}: {exc}")
        finally:
            conn.close()


LIMITS = SocketLimits(
    max_frame=MAX_FRAME, max_connections=8, idle_timeout_s=2.0, auth_timeout_s=0.5, max_pending=8
)


class Service:
    """The server's child process, its address and token, and the real client beside it."""

    def __init__(self) -> None:
        ctx = mp.get_context("spawn")
        self.pipe, theirs = ctx.Pipe()
        self.proc = ctx.Process(target=serve_in_child, args=(theirs, LIMITS), daemon=True)
        self.proc.start()
        address, token = self.pipe.recv()
        self.address, self.token = address, SocketToken.from_hex(token)
        # the answers alone: one client, nothing else on the socket
        alone = PolicySocketConnection(self.address, self.token, MAX_FRAME)
        want = [alone.infer(r, "real:0") for r in _requests()]
        alone.close()
        self.real = _RealClient(self.address, self.token, want)
        self.real.start()
        time.sleep(0.3)  # the client's connection and buffers settled
        self.rss0 = _rss_bytes(self.proc.pid)
        self.threads0 = _proc(self.proc.pid, "Threads")
        self.rss_max = self.rss0

    def report(self) -> dict[str, Any]:
        self.pipe.send("report")
        return self.pipe.recv()

    def close(self) -> None:
        self.real.stop.set()
        self.real.join(timeout=10)
        self.pipe.send("stop")
        self.proc.join(timeout=10)
        if self.proc.is_alive():
            self.proc.kill()


@pytest.fixture(scope="module")
def service():
    svc = Service()
    yield svc
    svc.close()


# -- what the fuzzer sends --------------------------------------------------------------------
def _valid_message() -> dict[str, Any]:
    return request_message(_requests()[0], "fuzz:0")


_leaf = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**64 - 1),
    st.floats(allow_nan=True),
    st.text(max_size=20),
    st.binary(max_size=20),
)
_values = st.recursive(
    _leaf,
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
_arrays = st.builds(
    lambda shape, dtype, fill: np.full(shape, fill, dtype=dtype),
    st.lists(st.integers(0, 5), min_size=0, max_size=5).map(tuple),
    st.sampled_from(["u1", "f4", "f8", "i8", "?", "c8"]),
    st.integers(0, 255),
)


@st.composite
def _wrong_shapes(draw) -> dict[str, Any]:
    """A real request with one field dropped, replaced by any value or array, or one added."""
    msg = _valid_message()
    key = draw(st.sampled_from(sorted(msg)))
    how = draw(st.sampled_from(["drop", "value", "array", "extra", "image"]))
    if how == "drop":
        del msg[key]
    elif how == "value":
        msg[key] = draw(_values)
    elif how == "array":
        msg[key] = draw(_arrays)
    elif how == "image":  # a camera of another size or dtype: shaped like one, not the env's
        msg["images"] = {"agentview": draw(_arrays)}
    else:
        msg[draw(st.text(min_size=1, max_size=8))] = draw(_values)
    return msg


def _frame(payload: bytes) -> bytes:
    return struct.pack("!I", len(payload)) + payload


ATTACKS = (
    *("no_token", "wrong_token", "short_token", "oversized", "truncated"),
    *("random", "wrong_length", "wrong_shape", "msgpack"),
)


@st.composite
def _attacks(draw) -> tuple[str, int, bytes]:
    """(kind, how many bytes of the run's auth frame go first, the bytes after them)."""
    kind = draw(st.sampled_from(ATTACKS))
    full = AUTH_FRAME_BYTES
    if kind == "no_token":
        return kind, 0, draw(st.binary(max_size=200))
    if kind == "wrong_token":
        return kind, 0, SocketToken.new().auth_frame() + _frame(wire.encode(_valid_message()))
    if kind == "short_token":  # a prefix of the right frame, then the peer stops
        return kind, draw(st.integers(0, full - 1)), b""
    if kind == "oversized":
        return kind, full, struct.pack("!I", draw(st.integers(MAX_FRAME + 1, 2**32 - 1)))
    if kind == "truncated":
        frame = _frame(wire.encode(_valid_message()))
        return kind, full, frame[: draw(st.integers(1, len(frame) - 1))]
    if kind == "random":
        return kind, full, _frame(draw(st.binary(min_size=1, max_size=300)))
    if kind == "wrong_length":  # a prefix that disagrees with the payload that follows
        payload = wire.encode(_valid_message())
        n = draw(st.integers(0, len(payload) + 64).filter(lambda k: k != len(payload)))
        return kind, full, struct.pack("!I", n) + payload
    if kind == "wrong_shape":
        return kind, full, _frame(wire.encode(draw(_wrong_shapes())))
    return kind, full, _frame(msgpack.packb(draw(_values), use_bin_type=True))


def _outcome(address, data: bytes) -> str:
    """Send ``data``, close our side for writing, and read what the server does: "closed",
    or "replied" with the replies it sent (each a well-formed reply map)."""
    s = socket.create_connection(address)
    try:
        s.settimeout(5.0)
        try:
            s.sendall(data)
            s.shutdown(socket.SHUT_WR)
        except OSError:  # the server closed it before all was sent
            return "closed"
        replies = []
        while True:
            try:
                replies.append(wire.recv(s, MAX_FRAME))
            except wire.WireError:  # EOF: the server closed it
                break
            except ConnectionResetError:
                break
        for r in replies:
            assert isinstance(r, dict) and isinstance(r.get("ok"), bool), r
        return "replied" if replies else "closed"
    finally:
        s.close()


@settings(
    max_examples=120,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(attack=_attacks())
def test_the_server_refuses_or_closes_whatever_it_is_sent(service, attack) -> None:
    kind, auth_bytes, body = attack
    outcome = _outcome(service.address, service.token.auth_frame()[:auth_bytes] + body)
    if kind in ("no_token", "wrong_token", "short_token", "oversized", "truncated"):
        assert outcome == "closed", kind  # nothing answered without the whole token and frame
    assert not service.real.problems, service.real.problems
    service.rss_max = max(service.rss_max, _rss_bytes(service.proc.pid))
    threads = _proc(service.proc.pid, "Threads")
    assert threads <= service.threads0 + LIMITS.max_connections


def test_after_the_fuzz_memory_threads_and_the_real_client_are_as_they_were(service) -> None:
    answered = service.real.answered
    time.sleep(0.3)
    assert service.real.answered > answered  # still answered, beside all the fuzzer sent
    assert not service.real.problems, service.real.problems
    report = service.report()
    assert report["escaped"] == []  # nothing raised out of a server thread
    # what the limits allow at once: each authenticated connection holds at most one frame (and
    # its thread's stack and malloc arena, a few hundred kB, well inside a frame bound here);
    # an announced length never allocates (the 4 GiB ones would show far above this)
    growth = max(service.rss_max, _rss_bytes(service.proc.pid)) - service.rss0
    allowed = LIMITS.max_connections * MAX_FRAME
    assert growth < allowed, f"RSS grew {growth} bytes, limits allow {allowed}"
    counts = report["socket"]
    refused = sum(v for k, v in counts.items() if k not in ("accepted", "answered", "active"))
    assert refused > 0 and counts["bad_token"] > 0 and counts["bad_request"] > 0
    assert counts["active"] <= LIMITS.max_connections
    # every request the real client sent was answered in a forward (none failed its batch)
    assert report["requests"] >= service.real.answered
