"""Forwards of one fixed shape on real networks (the tiny VLA, ACT built offline): a row's actions
are bit-identical whatever its position and batch mates, through the policy service whatever the
batch it arrives in, and equal to an in-actor IDRWrapper's on the same shape; a backbone whose
rows interact is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig

from training.toy_checkpoints import build_act
from workers.backbones.base import Observation, concat_observations
from workers.backbones.factory import make_backbone
from workers.policy.forward_shape import (
    FixedShapeBackbone,
    NumericsError,
    check_row_independence,
    fix_forward_shape,
    numerics_label,
    set_torch_threads,
    take_rows,
)
from workers.policy.service import InferRequest, PolicyWorker
from workers.policy.wrapper import IDRWrapper

ROOT = Path(__file__).resolve().parents[3]
TINY = ROOT / "checkpoints" / "tiny_vla"


@pytest.fixture(scope="module", params=["tiny_vla", "act"])
def real(request, tmp_path_factory) -> tuple[str, dict]:
    set_torch_threads(1)
    if request.param == "tiny_vla":
        if not (TINY / "config.json").exists():
            pytest.skip(f"{TINY} not built (make setup builds it)")
        return "lerobot", {"path": str(TINY), "device": "cpu"}
    path = build_act(tmp_path_factory.mktemp("act") / "act", cams=("agentview", "wrist"))
    return "lerobot", {"path": str(path), "device": "cpu"}


def _obs(backbone, n: int, seed: int) -> Observation:
    g = np.random.default_rng(seed)
    shape = next(iter(backbone.image_shapes.values()))
    return Observation(
        {c: torch.from_numpy(g.random((n, *shape), dtype=np.float32)) for c in backbone.cameras},
        torch.from_numpy(g.standard_normal((n, backbone.state_dim), dtype=np.float32)),
        ["put the red block on the blue one"] * n,
    )


def test_a_rows_actions_do_not_depend_on_position_or_mates_at_one_shape(real) -> None:
    backbone = make_backbone(*real)
    target, mates = _obs(backbone, 3, 0), _obs(backbone, 21, 1)
    fixed = FixedShapeBackbone(backbone, rows=12)
    alone = fixed.predict_chunk(target)  # padded with copies of itself
    for at in (0, 5, 9, 21):  # a batch of 24 rows: two forwards of 12
        before, after = take_rows(mates, np.arange(at)), take_rows(mates, np.arange(at, 21))
        parts = [p for p in (before, target, after) if p.batch_size]
        out = fixed.predict_chunk(concat_observations(parts))
        assert torch.equal(out[at : at + 3], alone), at
    check_row_independence(backbone, take_rows(target, np.arange(1)), None, 12)  # no raise


class FakeMixingBackbone:
    """FAKE: each row's action is shifted by the batch's mean state (rows interact)."""

    name = "fake_mixing"
    chunk_len, action_dim = 2, 3
    can_batch = True

    def reset(self) -> None: ...

    def make_noise(self, batch_size: int, seed: int) -> None:
        return None

    def predict_chunk(self, obs, noise=None, intervention=None):
        state = np.asarray(obs.state, dtype=np.float32)
        a = state[:, :3] + state.mean()
        return np.repeat(a[:, None, :], self.chunk_len, axis=1)


def test_a_backbone_whose_rows_interact_is_refused_naming_why() -> None:
    obs = Observation({}, np.ones((1, 4), np.float32), ["x"])
    with pytest.raises(NumericsError, match=r"fake_mixing.*forward of 8 rows.*batching=dynamic"):
        check_row_independence(FakeMixingBackbone(), obs, None, 8)


INSTRUCTIONS = ("pick up the red block", "put all the blocks in the bin one by one")


def _request(backbone, seed: int, idr: RefinerConfig) -> InferRequest:
    o = _obs(backbone, 1, seed)
    text = [INSTRUCTIONS[seed % 3 == 0]]  # two lengths: the tiny VLA packs its RNN by length
    plain = Observation({k: v.numpy() for k, v in o.images.items()}, o.state.numpy(), text)
    return InferRequest(plain, seed, idr, InterventionConfig(state_space="normalized"))


def test_the_service_answers_a_request_the_same_in_any_batch_and_as_in_actor(real) -> None:
    """Fixed shape: the same step for a request alone, first or last among others (with other
    instructions, of other lengths), in another order; and the same as an in-actor IDRWrapper
    given forwards of the same rows."""
    worker = PolicyWorker(*real, rows=12, threads=1)
    e, base = RefinerConfig(mode="E", tau=0.5), RefinerConfig(mode="baseline")
    reqs = [_request(worker.backbone, s, e) for s in range(1, 7)]
    first = worker.infer_many(reqs)
    again = worker.infer_many(reqs[::-1])[::-1]
    alone = [worker.infer_many([r])[0] for r in reqs]
    b = _request(worker.backbone, 7, base)  # a baseline's one row among IDR's three
    assert np.array_equal(
        worker.infer_many([*reqs, b])[-1].action, worker.infer_many([b])[0].action
    )
    for a, b, c in zip(first, again, alone, strict=True):
        assert np.array_equal(a.action, b.action) and np.array_equal(a.action, c.action)
        assert np.array_equal(a.a_base, c.a_base)
    assert worker.refusal is None and worker.numerics == "rows=12 threads=1"
    policy = IDRWrapper(make_backbone(*real))
    assert fix_forward_shape(policy, 12, 1) == "rows=12 threads=1"
    req = reqs[0]
    obs = Observation(
        {k: torch.from_numpy(v) for k, v in req.obs.images.items()},
        torch.from_numpy(req.obs.state),
        req.obs.instruction,
    )
    in_actor = policy.infer(obs, req.step_seed, e, InterventionConfig(state_space="normalized"))
    assert np.array_equal(in_actor.action.numpy(), first[0].action)
    assert np.array_equal(in_actor.diag.e_img.numpy(), first[0].diag.e_img)


def test_a_fixed_shape_service_refuses_every_request_of_a_backbone_whose_rows_interact(
    monkeypatch,
) -> None:
    import workers.backbones.factory as factory

    monkeypatch.setattr(factory, "make_backbone", lambda kind, params: FakeMixingBackbone())
    worker = PolicyWorker("fake", {}, rows=6)
    req = InferRequest(
        Observation({}, np.ones((1, 4), np.float32), ["x"]),
        0,
        RefinerConfig(),
        InterventionConfig(),
    )
    answers = worker.infer_each([req, req])
    assert all(isinstance(a, NumericsError) for a in answers)
    assert worker.forwards == 0  # nothing answered on a shape that does not hold


@pytest.mark.parametrize(
    ("args", "label"),
    [
        ((None, 1), "request threads=1"),
        ((96, 2), "rows=96 threads=2"),
        (("dynamic", 1), "dynamic threads=1"),
        ((96, 1, False), "per_pass threads=1"),
        ((96, 1, True, True), "remote"),
    ],
)
def test_numerics_labels(args, label) -> None:
    assert numerics_label(*args) == label
