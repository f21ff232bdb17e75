"""The policy service's batched forward: many episodes' requests in one backbone call give each
episode exactly what its own IDRWrapper.infer gives (same actions, same diagnostics)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig

from tests.doubles.backbones import CountingMarkerBackbone
from workers.backbones.base import Observation
from workers.backbones.fakes import FakeMarkerBackbone
from workers.envs.fakes import FakeMarkerEnv
from workers.episode.observation import to_policy_observation
from workers.policy.service import InferRequest, PolicyWorker, infer_many, to_numpy_step
from workers.policy.wrapper import IDRWrapper


def _requests(n: int) -> list[InferRequest]:
    env = FakeMarkerEnv()
    cells = [
        (RefinerConfig(mode="baseline"), InterventionConfig()),
        (RefinerConfig(mode="E"), InterventionConfig()),
        (RefinerConfig(mode="diagnose", alpha=0.2), InterventionConfig(strategy="gaussian")),
        (RefinerConfig(mode="A", tau=0.5), InterventionConfig(strategy="mean")),
    ]
    out = []
    for i in range(n):
        obs = env.reset("reach", i, 0)
        cfg, iv = cells[i % len(cells)]
        out.append(
            InferRequest(to_policy_observation(obs, obs.status.instruction), 1000 + i, cfg, iv)
        )
    return out


def _same(a, b) -> bool:
    a, b = to_numpy_step(a), to_numpy_step(b)
    same = np.array_equal(a.action, b.action) and np.array_equal(a.a_base, b.a_base)
    if a.diag is None or b.diag is None:
        return same and a.diag is None and b.diag is None
    return same and all(
        np.array_equal(a.diag.to_numpy()[k], b.diag.to_numpy()[k]) for k in a.diag.to_numpy()
    )


@pytest.mark.parametrize("noise_std", [0.0, 0.3], ids=["deterministic", "flow-like noise"])
def test_one_forward_for_many_episodes_gives_each_its_own_answer(noise_std):
    backbone = CountingMarkerBackbone(chunk_len=4, gain=5.0, noise_std=noise_std)
    requests = _requests(12)
    batched = infer_many(IDRWrapper(backbone), requests)
    assert backbone.calls == [3 * 9 + 3]  # one forward: 9 IDR cells x 3 rows + 3 baselines
    for req, got in zip(requests, batched, strict=True):
        alone = IDRWrapper(FakeMarkerBackbone(chunk_len=4, gain=5.0, noise_std=noise_std))
        assert _same(got, alone.infer(req.obs, req.step_seed, req.idr, req.intervention))
        assert got.crn == (noise_std > 0)


def test_an_answer_does_not_depend_on_its_batch_mates():
    requests = _requests(8)
    backbone = FakeMarkerBackbone(chunk_len=4, gain=5.0, noise_std=0.3)
    together = infer_many(IDRWrapper(backbone), requests)
    reordered = infer_many(IDRWrapper(backbone), requests[::-1])[::-1]
    apart = [infer_many(IDRWrapper(backbone), [r])[0] for r in requests]
    assert all(
        _same(a, b) and _same(a, c) for a, b, c in zip(together, reordered, apart, strict=True)
    )


def test_a_backbone_that_cannot_batch_answers_request_by_request():
    backbone = CountingMarkerBackbone(chunk_len=4, gain=5.0, can_batch=False)
    requests = _requests(4)
    infer_many(IDRWrapper(backbone), requests)
    assert backbone.calls == [1] + [1] * 9  # the baseline: 1 pass; each IDR cell: 3 passes


def test_the_worker_answers_numpy_to_numpy_requests():
    worker = PolicyWorker("fake_marker", {"chunk_len": 4, "gain": 5.0, "noise_std": 0.1})
    requests = _requests(5)
    plain = [
        InferRequest(
            Observation(
                {k: v.numpy() for k, v in r.obs.images.items()},
                r.obs.state.numpy(),
                r.obs.instruction,
            ),
            r.step_seed,
            r.idr,
            r.intervention,
        )
        for r in requests
    ]
    got = worker.infer_many(plain)
    assert all(isinstance(s.action, np.ndarray) for s in got)
    expected = infer_many(IDRWrapper(worker.backbone), requests)
    assert all(_same(a, b) for a, b in zip(got, expected, strict=True))
    assert worker.describe()["batched"] is True and worker.forwards == 1
    assert torch.is_tensor(requests[0].obs.state)  # the caller's requests are left as they were


def test_a_forward_out_of_memory_is_split_and_the_fitting_size_remembered():
    """12 requests (30 rows) on a FAKE device of 8 rows: halves, then quarters... down to
    forwards that fit; every answer equals the unsplit forward's, and the next batch is cut to
    the size that fit before its forward (no second out-of-memory)."""
    params = {"chunk_len": 4, "gain": 5.0, "noise_std": 0.3}
    requests = _requests(12)
    roomy = PolicyWorker("fake_marker", params)
    small = PolicyWorker(
        "tests.doubles.backbones:SmallDeviceMarkerBackbone", {**params, "max_rows": 8}
    )
    want = roomy.infer_each(requests)
    got = small.infer_each(requests)
    assert all(_same(a, b) for a, b in zip(want, got, strict=True))
    assert small.splits > 0 and small.fit is not None and small.fit <= 3
    raised = small.backbone.oom_raised
    again = small.infer_each(requests)
    assert small.backbone.oom_raised == raised  # cut to the remembered size: nothing raised
    assert all(_same(a, b) for a, b in zip(want, again, strict=True))


def test_only_a_request_that_fails_alone_is_an_error():
    requests = _requests(6)
    doomed = 3  # this one cannot fit even alone
    requests[doomed] = InferRequest(
        Observation(
            requests[doomed].obs.images,
            requests[doomed].obs.state,
            ["reach the marker HUGE"],
        ),
        requests[doomed].step_seed,
        requests[doomed].idr,
        requests[doomed].intervention,
    )
    worker = PolicyWorker(
        "tests.doubles.backbones:SmallDeviceMarkerBackbone",
        {"chunk_len": 4, "max_rows": 100, "always_oom": "HUGE"},
    )
    answers = worker.infer_each(requests)
    assert [isinstance(a, BaseException) for a in answers] == [i == doomed for i in range(6)]
    assert type(answers[doomed]).__name__ == "OutOfMemoryError"
    with pytest.raises(torch.OutOfMemoryError):
        worker.infer_many(requests)  # the old interface raises the request's error
