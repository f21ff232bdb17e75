"""The policy socket's door: only the run's token gets a connection past its first 40 bytes;
connections, frames and idle time are bounded and each refusal is counted; the run's token is
kept in the run dir with mode 0600 and never shows in a repr; the frame bound fits the env's
real requests. Loopback only."""

from __future__ import annotations

import os
import socket
import stat
import struct
import threading
import time
import tracemalloc

import numpy as np
import pytest
from idr_core.refiner import RefinerConfig

from pipeline.planning.executor_config import SharedExecutor
from pipeline.rundir import POLICY_TOKEN_FILE, policy_token
from workers.envs.fakes import FakeMarkerEnv
from workers.envs.server import wire
from workers.episode.observation import to_policy_observation
from workers.io_spec import EnvIO
from workers.policy.actor import PolicyServiceClient
from workers.policy.service import PolicyWorker
from workers.policy.socket_client import PolicySocketConnection
from workers.policy.socket_messages import request_message
from workers.policy.socket_server import PolicySocketServer
from workers.policy.socket_settings import (
    AUTH_FRAME_BYTES,
    RAY_CALLS,
    PolicyEndpoint,
    SocketLimits,
    SocketToken,
    connection_cap,
    frame_bound,
)

PARAMS = {"chunk_len": 4, "gain": 5.0, "noise_std": 0.2}
FAKE_IO = EnvIO(cameras=("agentview",), image_size=32, state_dim=2, action_dim=2)


def _request(episode: int = 0):
    o = FakeMarkerEnv().reset("reach", episode, 0)
    client = PolicyServiceClient(None, RAY_CALLS, cfg=RefinerConfig(mode="E"))
    return client.request(to_policy_observation(o, o.status.instruction), 100 + episode)


@pytest.fixture
def served():
    """A server answering with the fake policy, its token, and a closer."""
    worker = PolicyWorker("fake_marker", PARAMS)
    lock = threading.Lock()

    def answer(request, client):
        with lock:
            return worker.infer_many([request])[0]

    token = SocketToken.new()
    limits = SocketLimits(
        max_frame=frame_bound(FAKE_IO),
        max_connections=3,
        idle_timeout_s=1.0,
        auth_timeout_s=0.5,
        max_pending=4,
    )
    server = PolicySocketServer(answer, "127.0.0.1", token, limits)
    yield server, token
    server.close()


def _closed_by_peer(sock: socket.socket, timeout_s: float = 3.0) -> bool:
    """True when the server closes ``sock`` (EOF or reset) within ``timeout_s``."""
    sock.settimeout(timeout_s)
    try:
        while True:
            if not sock.recv(4096):
                return True
    except ConnectionResetError:
        return True
    except TimeoutError:
        return False


def _wait_for(predicate, timeout_s: float = 5.0) -> None:
    end = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < end, "timed out"
        time.sleep(0.01)


def test_the_token_answers_and_a_missing_or_wrong_one_is_closed_unread(served):
    server, token = served
    good = PolicySocketConnection(server.address, token)
    want = PolicyWorker("fake_marker", PARAMS).infer_many([_request()])[0]
    assert np.array_equal(good.infer(_request(), "c:0").action, want.action)

    for first in (
        SocketToken.new().auth_frame(),  # another run's token
        b"\x00" * AUTH_FRAME_BYTES,
        token.auth_frame()[:-1] + bytes([token.auth_frame()[-1] ^ 1]),  # one bit off
    ):
        s = socket.create_connection(server.address)
        # a wrong auth frame and a whole request behind it: the request is never read
        s.sendall(first + struct.pack("!I", 10) + b"x" * 10)
        assert _closed_by_peer(s)
        s.close()
    # a request without any auth frame: its first 40 bytes are taken as one, and refused
    s = socket.create_connection(server.address)
    wire.send(s, request_message(_request(), "c:x"))
    assert _closed_by_peer(s)
    s.close()
    _wait_for(lambda: server.stats().get("bad_token", 0) == 4)
    st = server.stats()
    assert st["accepted"] == 1 and st["answered"] == 1
    assert np.array_equal(good.infer(_request(), "c:0").action, want.action)
    good.close()


def test_a_silent_or_slow_peer_is_dropped_after_the_auth_timeout_and_holds_no_thread(served):
    server, token = served
    threads = threading.active_count()
    silent = [socket.create_connection(server.address) for _ in range(3)]
    silent[0].sendall(token.auth_frame()[:10])  # part of the right frame, never the rest
    assert threading.active_count() == threads  # waiting for auth costs no thread
    assert all(_closed_by_peer(s) for s in silent)
    assert server.stats()["auth_timeout"] == 3
    for s in silent:
        s.close()


def test_pending_connections_are_capped_and_the_oldest_dropped(served):
    server, token = served
    held = []
    for _ in range(10):  # max_pending 4
        held.append(socket.create_connection(server.address))
        time.sleep(0.005)
    _wait_for(lambda: server.stats().get("auth_evicted", 0) == 6)
    assert all(_closed_by_peer(s, 1.0) for s in held[:6])
    # a client with the token still gets in while the flood waits
    conn = PolicySocketConnection(server.address, token)
    assert conn.infer(_request(), "c:0").action.shape[-1] == 2
    conn.close()
    for s in held:
        s.close()


def test_connections_over_the_cap_are_refused_and_counted(served):
    server, token = served
    conns = [PolicySocketConnection(server.address, token) for _ in range(3)]  # the cap
    for i, c in enumerate(conns):
        c.infer(_request(i), f"c:{i}")
    extra = socket.create_connection(server.address)
    extra.sendall(token.auth_frame())
    assert _closed_by_peer(extra)
    assert server.stats()["over_cap"] == 1 and server.stats()["active"] == 3
    conns[0].close()  # a slot freed is taken again
    _wait_for(lambda: server.stats()["active"] == 2)
    again = PolicySocketConnection(server.address, token)
    assert again.infer(_request(), "c:9").action.shape[-1] == 2
    for c in [*conns[1:], again]:
        c.close()
    extra.close()


def test_an_idle_connection_is_closed_and_its_client_sends_again_on_a_new_one(served):
    server, token = served
    client = PolicyServiceClient(
        None, PolicyEndpoint("socket", server.address, token), cfg=RefinerConfig(mode="E")
    )
    o = FakeMarkerEnv().reset("reach", 0, 0)
    obs = to_policy_observation(o, o.status.instruction)
    first = client.infer(obs, 7)
    _wait_for(lambda: server.stats().get("idle_closed", 0) == 1, timeout_s=5)
    # the closed connection breaks on its next use: without a Ray handle to ask where the
    # actor is, the client says so (with one, it reconnects: policy/test_actor)
    with pytest.raises(Exception, match="cannot be reached"):
        client.infer(obs, 7)
    assert np.array_equal(client.infer(obs, 7).action, first.action)  # a new connection


def test_an_oversized_or_undecodable_frame_closes_its_connection_only(served):
    server, token = served
    good = PolicySocketConnection(server.address, token)
    for frame in (
        struct.pack("!I", server.limits.max_frame + 1),  # announced too large: nothing read
        struct.pack("!I", 16) + b"\xc1" * 16,  # 0xc1 is never valid msgpack
        struct.pack("!I", 3) + b"\x01\x02\x03",  # a number and trailing bytes
    ):
        s = socket.create_connection(server.address)
        s.sendall(token.auth_frame() + frame)
        assert _closed_by_peer(s)
        s.close()
    # a well-formed message of the wrong shape is answered with an error, connection kept
    s = socket.create_connection(server.address)
    s.sendall(token.auth_frame())
    wire.send(s, {"client": "x", "images": "not a map"})
    reply = wire.recv(s)
    assert reply["ok"] is False and reply["type"] == "ValueError"
    s.close()
    st = server.stats()
    assert st["oversized"] == 1 and st["malformed"] == 2 and st["bad_request"] == 1
    assert good.infer(_request(), "c:0").action.shape[-1] == 2
    good.close()


def test_a_length_prefix_alone_allocates_a_small_buffer_not_the_announced_size():
    """The issue's 1 GiB prefix: memory follows the bytes that arrive (traced allocations)."""
    a, b = socket.socketpair()
    announced, sent = 512 << 20, 3 << 20
    t = threading.Thread(
        target=lambda: (a.sendall(struct.pack("!I", announced) + b"\x00" * sent), a.close())
    )
    tracemalloc.start()
    t.start()
    with pytest.raises(wire.WireError, match="closed"):
        wire.recv(b)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    t.join()
    b.close()
    assert peak < 4 * sent < announced // 32


def test_the_frame_bound_holds_the_env_s_requests_with_headroom():
    req = request_message(_request(), "c:0")
    size = len(wire.encode(req))
    assert frame_bound(FAKE_IO) >= 2 * size
    # images dominate: two 224 px cameras as float32, doubled, plus the allowance
    big = EnvIO(cameras=("a", "b"), image_size=224, state_dim=8, action_dim=7)
    assert frame_bound(big) == 2 * (2 * 3 * 224 * 224 * 4 + 4 * 1024 * 7 * 8 + (1 << 20))
    assert frame_bound(big) < 5 << 20  # far below the wire's 1 GiB ceiling


def test_the_default_connection_cap_follows_the_episodes_in_flight():
    ex = SharedExecutor(workers=3, envs_per_worker=4, policy_actors=2)
    assert ex.episodes_per_policy_actor() == 8  # 2 of the 3 actors x 4 envs
    assert connection_cap(ex.episodes_per_policy_actor()) == 24
    assert SharedExecutor(workers=4, max_in_flight=2).episodes_per_policy_actor() == 2


def test_the_run_token_is_kept_0600_reused_and_never_shown(tmp_path):
    secret = policy_token(tmp_path)
    path = tmp_path / POLICY_TOKEN_FILE
    assert len(secret) == 32 and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert policy_token(tmp_path) == secret  # a resume talks with the same token
    os.chmod(path, 0o644)  # others could read it: no longer a secret, a new one is made
    renewed = policy_token(tmp_path)
    assert renewed != secret and stat.S_IMODE(path.stat().st_mode) == 0o600
    token = SocketToken(renewed)
    for shown in (repr(token), str(token), repr({"token": token}), f"{token}"):
        assert renewed.hex() not in shown and "SocketToken(...)" in shown
