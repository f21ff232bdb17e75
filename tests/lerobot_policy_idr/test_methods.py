"""The test-time methods' table and their arithmetic (idr_core.methods), model-free."""

from __future__ import annotations

import numpy as np
import pytest
from idr_core.methods import (
    METHODS,
    combine,
    forward_rows,
    passes,
    refusal,
    sample_seeds,
    unread_settings,
)
from idr_core.refiner import MODES, RefinerConfig, refine
from idr_core.three_pass import PassRequest, infer_requests

RNG = np.random.default_rng(0)
A, NO_IMG, NO_PROP, NO_OBJ = RNG.normal(size=(4, 3, 5, 2))


def test_every_mode_is_a_method_with_its_passes_and_cost() -> None:
    assert set(METHODS) == set(MODES)
    cost = {m: forward_rows(RefinerConfig(mode=m), b=2) for m in MODES}
    assert cost["baseline"] == cost["temporal"] == 2
    assert cost["cfg"] == cost["pcd"] == 4
    assert all(cost[m] == 6 for m in ("diagnose", "E", "F", "random", "shuffled", "scale_free"))
    assert cost["ensemble"] == 6  # K = 3 draws: IDR's forwards
    assert passes(RefinerConfig(mode="ensemble", samples=5)) == ("factual",) + ("sample",) * 4


def test_cfg_and_pcd_are_the_guidance_formula_without_gate_or_stabilizer() -> None:
    cfg = RefinerConfig(mode="cfg", w=0.7, tau=0.0)  # tau 0 would close E's gate
    got, diag = combine(cfg, [A, NO_IMG])
    np.testing.assert_allclose(got, A + 0.7 * (A - NO_IMG))
    assert diag is None
    got, _ = combine(RefinerConfig(mode="pcd", w=0.3), [A, NO_OBJ])
    np.testing.assert_allclose(got, A + 0.3 * (A - NO_OBJ))
    # cfg at w = alpha is D without its stabilizer: A with the gate open
    d, _ = refine(A, NO_IMG, NO_PROP, RefinerConfig(mode="A", tau=1e9))
    c, _ = combine(RefinerConfig(mode="cfg"), [A, NO_IMG])
    np.testing.assert_allclose(c, d)


def test_ensemble_is_the_mean_of_its_draws_and_temporal_the_factual_chunk() -> None:
    draws = [A, NO_IMG, NO_PROP]
    got, _ = combine(RefinerConfig(mode="ensemble"), draws)
    np.testing.assert_allclose(got, np.mean(draws, axis=0))
    got, _ = combine(RefinerConfig(mode="temporal"), [A])
    assert got is A
    with pytest.raises(ValueError, match="needs 3 forwards"):
        combine(RefinerConfig(mode="ensemble"), [A, A])


def test_sample_seeds_start_with_the_step_seed_and_differ() -> None:
    seeds = sample_seeds(1234, 4)
    assert seeds[0] == 1234 and len(set(seeds)) == 4
    assert seeds == sample_seeds(1234, 4)


def test_a_method_names_the_settings_it_ignores() -> None:
    assert unread_settings(RefinerConfig(mode="cfg"), ["w", "alpha", "tau"]) == ["alpha", "tau"]
    assert unread_settings(RefinerConfig(mode="E"), ["w", "alpha", "samples"]) == ["w", "samples"]
    assert unread_settings(RefinerConfig(mode="temporal"), ["horizon", "te_coeff"]) == ["horizon"]


@pytest.mark.parametrize(
    ("mode", "facts", "words"),
    [
        ("ensemble", {"samples": False}, "deterministic"),
        ("temporal", {"chunk_len": 1}, "one action per inference"),
        ("pcd", {"hidden_objects": False}, "on a robot"),
    ],
)
def test_refusals_name_the_method_the_base_or_suite_and_why(mode, facts, words) -> None:
    kw = {"samples": None, "chunk_len": None, "hidden_objects": None, **facts}
    why = refusal(RefinerConfig(mode=mode), base="act", suite="metaworld", **kw)
    assert why is not None and repr(mode) in why and words in why
    unknown = {**kw, **dict.fromkeys(facts)}
    assert refusal(RefinerConfig(mode=mode), base="act", suite="x", **unknown) is None


def _call(inputs: np.ndarray, noise: np.ndarray | None) -> np.ndarray:
    """A fake sampling policy: the input plus its noise."""
    return inputs if noise is None else inputs + noise


@pytest.mark.parametrize("batched", [True, False])
def test_an_ensemble_request_gives_each_draw_its_own_noise(batched: bool) -> None:
    x = np.zeros((1, 5, 2))
    noises = tuple(np.full((1, 5, 2), float(k)) for k in (1, 2, 6))
    req = PassRequest(
        x, (x, x), noises[0], RefinerConfig(mode="ensemble"), 1, seed=0, noises=noises
    )
    # a batch mate of another method, packed into the same forward
    mate = PassRequest(x + 1, None, np.zeros((1, 5, 2)), RefinerConfig(mode="baseline"), 1)
    res, other = infer_requests(
        _call,
        [req, mate],
        concat=np.concatenate,
        concat_noise=np.concatenate,
        batched=batched,
    )
    np.testing.assert_allclose(res.action, np.full((1, 5, 2), 3.0))  # mean of 1, 2, 6
    np.testing.assert_allclose(res.a_base, noises[0])
    assert res.rows == 3 and res.diag is None and res.a_no_img is None
    np.testing.assert_allclose(other.action, x + 1)
    assert other.rows == 1
