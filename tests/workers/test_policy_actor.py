"""The policy actor: concurrent requests batched into few forwards, each answered as alone;
images cross as the uint8 they were made from."""

from __future__ import annotations

import pickle
import time

import numpy as np
import pytest
import torch

from workers.backbones.fakes import FakeMarkerBackbone
from workers.envs.fakes import FakeMarkerEnv
from workers.idr import RefinerConfig
from workers.idr_wrapper import IDRWrapper
from workers.observation import image_to_tensor, to_policy_observation
from workers.policy_actor import (
    RECENT_FORWARDS,
    BatchingPolicyActor,
    PolicyServiceClient,
    _image_bytes,
    policy_actor_class,
)


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
    remote = PolicyServiceClient(actor, ray_local.get(actor.describe.remote()))
    env = FakeMarkerEnv()
    observations = [
        to_policy_observation(env.reset("reach", e, 0), env.instruction) for e in range(12)
    ]
    remote.set_config(RefinerConfig(mode="E"))
    # sent at once, as the proxy sends each (pickled requests, pickled answers)
    refs = [
        actor.infer.remote(pickle.dumps(remote.request(o, 100 + i), protocol=5))
        for i, o in enumerate(observations)
    ]
    answers = [pickle.loads(a) for a in ray_local.get(refs)]
    stats = ray_local.get(actor.stats.remote())
    assert stats["requests"] == 12 and stats["forwards"] < 12  # batched while the first computed
    local = IDRWrapper(FakeMarkerBackbone(**params))
    local.set_config(RefinerConfig(mode="E"))
    for i, (o, got) in enumerate(zip(observations, answers, strict=True)):
        want = local.infer(o, 100 + i)
        assert np.array_equal(got.action, want.action.numpy())
        assert np.array_equal(got.diag.e_img, want.diag.e_img.numpy())
    # the proxy's own path: one Ray call per inference, the same answer
    again = remote.infer(observations[3], 103)
    assert np.array_equal(again.action, answers[3].action)
    ray_local.kill(actor)


def test_a_lone_client_does_not_wait_for_batch_mates():
    """The batcher waits only for as many requests as recent forwards held: requests sent one
    after another go at once although the batching wait is 30 s (a crowd is still batched:
    test_concurrent_requests_share_forwards_and_get_their_own_answers)."""
    actor = BatchingPolicyActor("fake_marker", {"chunk_len": 4}, None, 16, 30_000)
    client = PolicyServiceClient(None, actor.describe())
    client.set_config(RefinerConfig(mode="E"))
    env = FakeMarkerEnv()
    obs = to_policy_observation(env.reset("reach", 0, 0), env.instruction)
    took = []
    for i in range(2 * RECENT_FORWARDS):
        t0 = time.monotonic()
        step = pickle.loads(actor.infer(pickle.dumps(client.request(obs, i), protocol=5)))
        took.append(time.monotonic() - t0)
        assert step.action.shape == (1, 4, 2)
    assert max(took) < 10  # never the 30 s wait
    assert actor.stats()["forwards"] == 2 * RECENT_FORWARDS
