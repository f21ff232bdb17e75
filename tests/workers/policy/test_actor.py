"""The policy actor: concurrent requests batched into few forwards, each answered as alone;
images cross as the uint8 they were made from."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch
from idr_core.refiner import RefinerConfig

from workers.backbones.fakes import FakeMarkerBackbone
from workers.envs.fakes import FakeMarkerEnv
from workers.episode.observation import image_to_tensor, to_policy_observation
from workers.policy.actor import PolicyServiceClient, _image_bytes, connect, policy_actor_class
from workers.policy.socket_client import PolicySocketConnection
from workers.policy.socket_settings import (
    RAY_CALLS,
    PolicyEndpoint,
    SocketLimits,
    SocketSettings,
    SocketToken,
)
from workers.policy.wrapper import IDRWrapper


def test_images_cross_as_their_bytes_and_come_back_the_same_floats():
    img = np.random.default_rng(0).integers(0, 256, (64, 64, 3), dtype=np.uint8)
    x = image_to_tensor(img)
    u8 = _image_bytes(x)
    assert u8.dtype == np.uint8 and u8.nbytes * 4 == x.numpy().nbytes
    assert torch.equal(torch.from_numpy(u8).float() / 255.0, x)
    noisy = x + 1e-3  # not made from a uint8 image: sent as it is
    assert _image_bytes(noisy).dtype == np.float32


@pytest.mark.slow
def test_concurrent_requests_share_forwards_and_get_their_own_answers(ray_local):
    params = {"chunk_len": 4, "gain": 5.0, "noise_std": 0.2, "delay_s": 0.05}
    actor = policy_actor_class(0.5, 0).remote("fake_marker", params, None, 16, 20.0)
    remote = connect(actor, RefinerConfig(mode="E"))
    env = FakeMarkerEnv()
    resets = [env.reset("reach", e, 0) for e in range(12)]
    observations = [to_policy_observation(o, o.status.instruction) for o in resets]
    # sent at once, each as the proxy sends it
    refs = [actor.infer.remote(remote.request(o, 100 + i)) for i, o in enumerate(observations)]
    answers = ray_local.get(refs)
    stats = ray_local.get(actor.stats.remote())
    assert stats["requests"] == 12 and stats["forwards"] < 12  # batched while the first computed
    local = IDRWrapper(FakeMarkerBackbone(**params), RefinerConfig(mode="E"))
    for i, (o, got) in enumerate(zip(observations, answers, strict=True)):
        want = local.infer(o, 100 + i)
        assert np.array_equal(got.action, want.action.numpy())
        assert np.array_equal(got.diag.e_img, want.diag.e_img.numpy())
    # the proxy's own path, over the actor's socket: the same answer
    assert remote.endpoint.transport == "socket"
    again = remote.infer(observations[3], 103)
    assert np.array_equal(again.action, answers[3].action)
    # and as one Ray call per inference (executor.policy_transport=ray)
    by_ray = PolicyServiceClient(actor, RAY_CALLS, remote.info, RefinerConfig(mode="E"))
    assert np.array_equal(by_ray.infer(observations[3], 103).action, answers[3].action)
    remote.close()
    ray_local.kill(actor)


def _requests(n: int) -> tuple[PolicyServiceClient, list]:
    env = FakeMarkerEnv()
    client = PolicyServiceClient(None, RAY_CALLS, cfg=RefinerConfig(mode="E"))
    resets = [env.reset("reach", e, 0) for e in range(n)]
    obs = [to_policy_observation(o, o.status.instruction) for o in resets]
    return client, [client.request(o, i) for i, o in enumerate(obs)]


def test_a_batch_goes_once_every_recent_client_has_a_request_in_it():
    """The batch wait (here 60 s) is cut short once each client heard from has asked: a lone
    client is answered at once, three closed loops share one forward; a request naming no
    client still waits the batch out (up to max_batch)."""
    import threading
    import time

    from workers.policy.actor import BatchingPolicyActor

    actor = BatchingPolicyActor("fake_marker", {"chunk_len": 4}, None, 16, 60_000.0)
    _, reqs = _requests(3)
    answers: dict[int, object] = {}

    def ask(i: int, client: str | None) -> None:
        answers[i] = actor.infer(reqs[i], client)

    lone = threading.Thread(target=ask, args=(0, "a"))
    lone.start()
    lone.join(timeout=20)
    assert not lone.is_alive() and actor.stats()["forwards"] == 1
    actor._last_seen.clear()  # "a" gone: three new clients, one request each
    for c in ("x", "y", "z"):
        actor._last_seen[c] = time.monotonic()
    threads = [threading.Thread(target=ask, args=(i, c)) for i, c in enumerate("xyz")]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=20)
    assert not any(t.is_alive() for t in threads)
    assert actor.stats()["forwards"] == 2 and actor.stats()["requests"] == 4  # one forward of 3
    anonymous = threading.Thread(target=ask, args=(1, None), daemon=True)
    anonymous.start()
    anonymous.join(timeout=2)
    assert anonymous.is_alive()  # no client named: it waits for others, up to the batch wait


def test_a_lone_clients_request_runs_in_its_thread_unless_a_forward_is_running():
    """A lone client with nothing queued is served in the Ray thread that received its request
    (no batcher hand-off), with the answer the batcher gives the same request; while a forward
    runs, its request waits and goes through the batcher."""
    import threading

    import numpy as np

    from workers.policy.actor import BatchingPolicyActor

    actor = BatchingPolicyActor("fake_marker", {"chunk_len": 4}, None, 16, 1.0)
    ran_in: list[str] = []
    infer_each = actor.worker.infer_each

    def traced(requests: list) -> list:
        ran_in.append(threading.current_thread().name)
        return infer_each(requests)

    actor.worker.infer_each = traced  # type: ignore[method-assign]
    _, reqs = _requests(1)
    here = actor.infer(reqs[0], "a")
    assert ran_in == [threading.current_thread().name]

    answers: list = []
    actor._forward.acquire()  # a forward in progress
    asker = threading.Thread(target=lambda: answers.append(actor.infer(reqs[0], "a")))
    asker.start()
    asker.join(timeout=0.5)
    assert asker.is_alive() and len(ran_in) == 1  # it waits for the running forward
    actor._forward.release()
    asker.join(timeout=20)
    assert not asker.is_alive() and ran_in[-1] == "batcher"
    (there,) = answers
    for field in ("action", "a_base", "a_no_img", "a_no_prop"):
        np.testing.assert_array_equal(np.asarray(getattr(here, field)), getattr(there, field))


@pytest.mark.slow
def test_a_client_closed_at_a_full_connection_cap_gets_in_once_a_slot_frees(ray_local):
    """Connections past the cap are closed at once: the client's tries are spaced, so a cap
    held full for a moment (another process's burst) costs a wait, not the episode."""
    token = SocketToken.new()
    settings = SocketSettings("127.0.0.1", token, SocketLimits(max_connections=2))
    params = {"chunk_len": 4, "gain": 5.0, "noise_std": 0.2}
    actor = policy_actor_class(0.5, 0).remote(
        "fake_marker", params, None, 4, 1.0, socket_settings=settings
    )
    o = FakeMarkerEnv().reset("reach", 0, 0)
    obs = to_policy_observation(o, o.status.instruction)
    remote = connect(actor, RefinerConfig(mode="E"))
    holders = [PolicySocketConnection(remote.endpoint.address, token) for _ in range(2)]
    alone = [h.infer(remote.request(obs, 7), f"h:{i}") for i, h in enumerate(holders)]
    release = threading.Timer(0.3, lambda: [h.close() for h in holders])
    release.start()
    got = remote.infer(obs, 7)  # sent while both slots are held
    release.join()
    assert np.array_equal(got.action, alone[0].action)
    remote.close()
    ray_local.kill(actor)


def test_the_client_gets_the_actors_transport_as_a_typed_endpoint():
    """The actor says where its requests go as a PolicyEndpoint (socket: its address and the
    run's token; ray: neither); a client given the socket one is answered over it as the actor
    answers the same request, and the token never shows in a repr."""
    from workers.policy.actor import BatchingPolicyActor

    token = SocketToken.new()
    settings = SocketSettings("127.0.0.1", token)
    actor = BatchingPolicyActor(
        "fake_marker", {"chunk_len": 4}, None, 4, 1.0, socket_settings=settings
    )
    endpoint = actor.endpoint()
    assert isinstance(endpoint, PolicyEndpoint) and endpoint.transport == "socket"
    host, port = endpoint.address
    assert host == "127.0.0.1" and isinstance(port, int) and endpoint.token == token
    assert token.hex() not in repr(endpoint) and "socket" not in actor.describe()
    _, reqs = _requests(1)  # the same observation, seed and cell as below
    over_socket = PolicyServiceClient(None, endpoint, actor.describe(), RefinerConfig(mode="E"))
    env = FakeMarkerEnv()
    o = env.reset("reach", 0, 0)
    got = over_socket.infer(to_policy_observation(o, o.status.instruction), 0)
    assert np.array_equal(got.action, actor.infer(reqs[0], "c").action)
    over_socket.close()
    actor._socket.close()
    ray_calls = BatchingPolicyActor("fake_marker", {"chunk_len": 4}, None, 4, 1.0, transport="ray")
    assert ray_calls.endpoint() == RAY_CALLS and RAY_CALLS.address is None
    with pytest.raises(ValueError, match="needs its address and the run's token"):
        PolicyEndpoint("socket")
    with pytest.raises(ValueError, match="no address"):
        PolicyEndpoint("ray", ("127.0.0.1", 1))
