"""McNemar power (Connor 1987) and Holm's correction against published worked examples, by-hand
values and properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.results import power as pw

Z975, Z80 = 1.959963984540054, 0.8416212335729143  # z_{1 - 0.05/2}, z_{0.80}


def test_connor_sample_size_worked_example() -> None:
    # powerandsamplesize.com (HyLown), "Compare Paired Proportions: McNemar's Z-test, 2-Sided
    # Equality", citing Connor (1987) p. 209: p01 = 0.45, p10 = 0.05, alpha = 0.05,
    # beta = 0.20 -> ceiling(n) = 23 pairs
    assert pw.pairs_needed(0.05 - 0.45, 0.05 + 0.45) == 23
    assert pw.pairs_needed(0.45 - 0.05, 0.50) == 23  # either direction
    # and its power formula (both tails) at the unrounded n gives the 80% back
    n = ((Z975 * math.sqrt(0.5) + Z80 * math.sqrt(0.5 - 0.16)) / 0.4) ** 2
    assert n == pytest.approx(22.0113, abs=1e-4)
    assert pw.mcnemar_power(n, 0.5, -0.4) == pytest.approx(0.80, abs=1e-6)


def test_connor_sample_size_second_example() -> None:
    # clinicaltrials-tools McNemar calculator ("McNemar's Test (Connor 1987)"): total
    # discordant proportion 0.45, |p10 - p01| = 0.15 (discordant odds ratio 2), alpha = 0.05
    # two-sided, 80% power -> 155 pairs, achieved power 80.1%
    assert pw.pairs_needed(0.15, 0.45) == 155
    assert pw.mcnemar_power(155, 0.45, 0.15) == pytest.approx(0.801, abs=5e-4)


@pytest.mark.parametrize(
    ("paid", "psi", "power", "want"),
    [
        # the examples of MESS::power_mcnemar_test (R), method "normal": paid = p12 (the smaller
        # discordant probability), psi = p21 / p12; its power expression is Connor's with
        # discordance paid (1 + psi) and difference paid (psi - 1). n = 233.09 and 247.997.
        (0.1, 2.0, 0.80, 234),
        (0.125, 2.0, 0.90, 248),
    ],
)
def test_mess_power_mcnemar_test_examples(paid, psi, power, want) -> None:
    disc, diff = paid * (1 + psi), paid * (psi - 1)
    assert pw.pairs_needed(diff, disc, power=power) == want


def test_mde_inverts_the_sample_size() -> None:
    # the worked example backwards: 22.0113 pairs at discordance 0.5 detect exactly 0.4
    n = ((Z975 * math.sqrt(0.5) + Z80 * math.sqrt(0.5 - 0.16)) / 0.4) ** 2
    assert pw.minimum_detectable_effect(n, 0.5) == pytest.approx(0.4, abs=1e-12)
    # by hand from the closed form: n = 200, psi = 0.2
    root = (Z975 * math.sqrt(40) + Z80 * math.sqrt(0.2 * (200 + Z80**2 - Z975**2))) / (200 + Z80**2)
    assert root == pytest.approx(0.088073, abs=1e-6)
    assert pw.minimum_detectable_effect(200, 0.2) == pytest.approx(root, rel=1e-12)


def test_edge_cases_are_inf_or_nan_with_a_reason() -> None:
    none = pw.paired_power(0, 0)
    assert math.isinf(none.mde) and math.isnan(none.pairs_for_1pp) and math.isnan(none.discordance)
    assert "no pairs" in none.note

    agree = pw.paired_power(50, 0)  # every pair concordant: McNemar has nothing to count
    assert agree.discordance == 0.0
    assert (
        math.isinf(agree.mde)
        and math.isinf(agree.pairs_for_1pp)
        and math.isinf(agree.pairs_for_5pp)
    )
    assert "no discordant pairs in 50" in agree.note
    assert pw.mcnemar_power(50, 0.0, 0.0) == 0.0

    # 2 discordant pairs of 50: even both going one way (4 pp) stays below 80% power, and a
    # 5 pp difference cannot happen with 4% discordant pairs; 1 pp can, with 3,138 pairs
    few = pw.paired_power(50, 2)
    assert math.isinf(few.mde) and math.isinf(few.pairs_for_5pp)
    assert few.pairs_for_1pp == 3138
    assert "all 2 discordant pairs of 50" in few.note and "at least 5% discordant" in few.note

    assert math.isinf(pw.minimum_detectable_effect(3, 1.0))  # n <= z_a^2 - z_b^2 (about 3.1)
    assert math.isinf(pw.pairs_needed(0.0, 0.3))
    with pytest.raises(ValueError, match=r"at least 0\.5 discordant"):
        pw.mcnemar_power(100, 0.2, 0.5)
    with pytest.raises(ValueError, match="discordant <= n_pairs"):
        pw.paired_power(5, 6)
    with pytest.raises(ValueError, match="power must lie"):
        pw.pairs_needed(0.1, 0.3, power=0.4)
    with pytest.raises(ValueError, match="alpha must lie"):
        pw.minimum_detectable_effect(10, 0.3, alpha=0.0)


def test_paired_power_of_a_typical_comparison() -> None:
    p = pw.paired_power(200, 40)  # 20% discordant pairs
    assert (p.discordance, p.note) == (0.2, "")
    assert p.mde_pp == pytest.approx(8.8073, abs=1e-4)
    # by hand: ((1.95996 sqrt(.2) + 0.84162 sqrt(.2 - d^2)) / d)^2 rounded up
    for pp, want in ((1, 15696), (5, 626)):
        d = pp / 100
        n = ((Z975 * math.sqrt(0.2) + Z80 * math.sqrt(0.2 - d * d)) / d) ** 2
        assert math.ceil(n) == want
    assert (p.pairs_for_1pp, p.pairs_for_5pp) == (15696, 626)


@settings(max_examples=200, deadline=None)
@given(
    st.integers(1, 5000),
    st.integers(1, 5000),
    st.floats(0.001, 1.0),
)
def test_mde_does_not_grow_with_pairs(n1, n2, psi) -> None:
    lo, hi = sorted((n1, n2))
    assert pw.minimum_detectable_effect(hi, psi) <= pw.minimum_detectable_effect(lo, psi)


@settings(max_examples=200, deadline=None)
@given(st.integers(4, 100_000), st.floats(0.001, 1.0))
def test_mde_has_the_power_it_claims(n, psi) -> None:
    d = pw.minimum_detectable_effect(n, psi)
    if math.isinf(d):
        # undetectable: even the largest possible difference (all discordance one way) is weak
        assert pw.mcnemar_power(n, psi, psi) < pw.POWER + 1e-9
        return
    assert 0 < d <= psi
    # Connor's n ignores the far tail; the two-sided power adds at most alpha / 2
    assert pw.POWER - 1e-9 <= pw.mcnemar_power(n, psi, d) <= pw.POWER + pw.ALPHA / 2
    assert pw.pairs_needed(d, psi) in (n, n + 1)  # round trip, up to rounding


@settings(max_examples=200, deadline=None)
@given(st.floats(0.001, 0.5), st.floats(0.001, 1.0))
def test_pairs_needed_reach_the_power(d, psi) -> None:
    n = pw.pairs_needed(d, psi)
    if d > psi:
        assert math.isinf(n)
        return
    assert pw.mcnemar_power(n, psi, d) >= pw.POWER - 1e-9
    if n > 1:
        assert pw.mcnemar_power(n - 1, psi, d) < pw.POWER + pw.ALPHA / 2


def test_holm_worked_example_rejections() -> None:
    # Holm-Bonferroni method (Wikipedia's example): four hypotheses, alpha = 0.05, raw p-values
    # 0.01, 0.04, 0.03, 0.005: H4 (0.005 < 0.05/4) and H1 (0.01 < 0.05/3) are rejected, then
    # 0.03 > 0.05/2 stops the procedure, so H3 and H2 are not
    adj = pw.holm([0.01, 0.04, 0.03, 0.005])
    # adjusted (Wright 1992): 4 x 0.005, max(0.02, 3 x 0.01), max(0.03, 2 x 0.03), max(0.06, 0.04)
    np.testing.assert_allclose(adj, [0.03, 0.06, 0.06, 0.02], rtol=1e-12)
    assert (adj <= 0.05).tolist() == [True, False, False, True]


def test_holm_published_adjusted_values() -> None:
    # stdlib-js @stdlib/stats/padjust, method 'holm': [0.319, 0.201, 0.4, 0.374, 0.113] ->
    # [~0.957, 0.804, ..., ~0.957, ~0.565] (the elided one is 0.957 too: max(0.957, 2 x 0.374))
    np.testing.assert_allclose(
        pw.holm([0.319, 0.201, 0.4, 0.374, 0.113]), [0.957, 0.804, 0.957, 0.957, 0.565], rtol=1e-12
    )


def test_holm_caps_at_one_and_keeps_nan() -> None:
    np.testing.assert_allclose(pw.holm([0.5, 0.6, 0.01]), [1.0, 1.0, 0.03])
    adj = pw.holm([0.02, float("nan"), 0.04])  # NaN left out of m, as R's p.adjust does
    assert math.isnan(adj[1])
    np.testing.assert_allclose(adj[[0, 2]], [0.04, 0.04])
    assert pw.holm([]).size == 0
    np.testing.assert_allclose(pw.holm([0.03, 0.03]), [0.06, 0.06])  # ties stay tied
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        pw.holm([0.2, 1.5])


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(0.0, 1.0), min_size=1, max_size=40))
def test_holm_properties(p) -> None:
    raw = np.asarray(p)
    adj = pw.holm(raw)
    m = raw.size
    assert np.all(adj >= raw) and np.all(adj <= 1.0)
    assert np.all(adj <= np.minimum(m * raw, 1.0) + 1e-15)  # never worse than Bonferroni
    order = np.argsort(raw, kind="stable")
    assert np.all(np.diff(adj[order]) >= 0)  # monotone in the raw order
    # rejections at 0.05 are exactly the step-down procedure's
    reject, alive = np.zeros(m, bool), True
    for rank, i in enumerate(order):
        alive = alive and raw[i] <= 0.05 / (m - rank)
        reject[i] = alive
    assert ((adj <= 0.05) == reject).all()
