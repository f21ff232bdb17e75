"""The policy actor's socket: a request and its answer cross it exactly (arrays, configs, the
diagnostics), a request's error comes back as that request's error with the connection kept,
and a server that goes away is reported, never answered from anywhere else."""

from __future__ import annotations

import math

import numpy as np
import pytest
from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig

from workers.envs.fakes import FakeMarkerEnv
from workers.envs.server import wire
from workers.episode.observation import to_policy_observation
from workers.policy.actor import PolicyServiceClient
from workers.policy.service import InferRequest, PolicyWorker
from workers.policy.socket_client import PolicyServiceError, PolicySocketConnection
from workers.policy.socket_messages import (
    request_from_message,
    request_message,
    step_from_message,
    step_message,
)
from workers.policy.socket_server import PolicySocketServer
from workers.policy.socket_settings import RAY_CALLS, PolicyEndpoint, SocketToken
from workers.policy.wrapper import IDRStep

PARAMS = {"chunk_len": 4, "gain": 5.0, "noise_std": 0.2}


def _request(episode: int = 0, **idr) -> InferRequest:
    o = FakeMarkerEnv().reset("reach", episode, 0)
    client = PolicyServiceClient(
        None,
        RAY_CALLS,
        cfg=RefinerConfig(mode="E", tau=math.inf, **idr),
        intervention=InterventionConfig(strategy="mean"),
    )
    return client.request(to_policy_observation(o, o.status.instruction), 100 + episode)


def _through_the_wire(msg):
    return wire.decode(wire.encode(msg))


def test_a_request_and_its_step_cross_the_wire_unchanged():
    req = _request(alpha=0.2)
    got, client = request_from_message(_through_the_wire(request_message(req, "c:1")))
    assert client == "c:1" and got.step_seed == req.step_seed
    assert got.idr == req.idr and got.idr.tau == math.inf and got.intervention == req.intervention
    assert got.obs.instruction == req.obs.instruction
    for cam, img in req.obs.images.items():  # uint8 bytes, as over Ray
        assert got.obs.images[cam].dtype == img.dtype == np.uint8
        assert np.array_equal(got.obs.images[cam], img)
    assert (
        np.array_equal(got.obs.state, req.obs.state) and got.obs.state.dtype == req.obs.state.dtype
    )

    step = PolicyWorker("fake_marker", PARAMS).infer_many([req])[0]
    back = step_from_message(_through_the_wire(step_message(step)))
    assert isinstance(back, IDRStep) and back.crn == step.crn and back.batched == step.batched
    assert back.inference_ms == step.inference_ms
    for name in ("action", "a_base", "a_no_img", "a_no_prop"):
        assert np.array_equal(getattr(back, name), getattr(step, name))
    for name, value in step.diag.to_numpy().items():
        assert np.array_equal(getattr(back.diag, name), value)


def test_a_baseline_step_has_no_counterfactuals_and_crosses_as_none():
    req = _request()
    req = InferRequest(req.obs, req.step_seed, RefinerConfig(mode="baseline"), req.intervention)
    step = PolicyWorker("fake_marker", PARAMS).infer_many([req])[0]
    back = step_from_message(_through_the_wire(step_message(step)))
    assert back.diag is None and back.a_no_img is None
    assert np.array_equal(back.action, step.action)


def test_a_server_answers_each_request_as_its_worker_does_and_returns_errors():
    worker = PolicyWorker("fake_marker", PARAMS)
    seen: list[str | None] = []

    def answer(request: InferRequest, client: str | None) -> IDRStep:
        seen.append(client)
        if request.step_seed == 666:
            raise ValueError("seed 666 refused")
        return worker.infer_many([request])[0]

    token = SocketToken.new()
    server = PolicySocketServer(answer, "127.0.0.1", token)
    conn = PolicySocketConnection(server.address, token)
    for e in range(3):
        req = _request(e)
        got = conn.infer(req, f"c:{e}")
        want = PolicyWorker("fake_marker", PARAMS).infer_many([req])[0]
        assert np.array_equal(got.action, want.action)
        assert np.array_equal(got.diag.e_img, want.diag.e_img)
    bad = _request()
    bad = InferRequest(bad.obs, 666, bad.idr, bad.intervention)
    with pytest.raises(PolicyServiceError, match="ValueError: seed 666 refused"):
        conn.infer(bad, "c:9")
    # the connection stays usable after a request's error
    assert np.array_equal(
        conn.infer(_request(1), "c:1").action, worker.infer_many([_request(1)])[0].action
    )
    assert seen == ["c:0", "c:1", "c:2", "c:9", "c:1"]
    conn.close()
    server.close()


def test_a_client_whose_actor_is_gone_is_told_so_after_its_tries():
    token = SocketToken.new()
    server = PolicySocketServer(lambda r, c: None, "127.0.0.1", token)
    address = server.address
    server.close()
    client = PolicyServiceClient(  # no Ray handle to ask again
        None, PolicyEndpoint("socket", address, token), cfg=RefinerConfig(mode="E")
    )
    o = FakeMarkerEnv().reset("reach", 0, 0)
    with pytest.raises(PolicyServiceError, match=r"cannot be reached .*ConnectionRefused"):
        client.infer(to_policy_observation(o, o.status.instruction), 0)
