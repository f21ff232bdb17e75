"""What a paired comparison of binary outcomes could have detected, and Holm's correction.

- ``minimum_detectable_effect``: the smallest difference in success rate that a paired
  comparison of ``n`` pairs detects with McNemar's test (two-sided alpha = 0.05) at 80% power,
  given its own share of discordant pairs, so that "no effect" reads "no effect above X pp";
- ``pairs_needed``: the pairs such a comparison needs for a given difference (1 pp, 5 pp) at
  that share of discordant pairs;
- ``paired_power``: both for one comparison from its counts, with the reason wherever a figure
  is undefined (the fields of ``aggregate.PairedDiff``);
- ``holm``: Holm's (1979) step-down adjusted p-values of a family of tests.

The power figures use Connor's (1987) normal approximation for McNemar's test (Connor, R. J.
1987. Sample size for testing differences in proportions for the paired-sample design.
Biometrics 43(1): 207-211, p. 209), not Miettinen's (1968) variant. With ``psi`` the share of
discordant pairs (p10 + p01) and ``delta`` the difference in success rates (p10 - p01):

    n = (z_{1-alpha/2} sqrt(psi) + z_{1-beta} sqrt(psi - delta^2))^2 / delta^2

The discordance rate is held at the comparison's own (conditional, as PROC POWER's McNemar
tests are): a difference can never exceed it (|p10 - p01| <= p10 + p01).

Written by hand rather than taken from statsmodels: statsmodels has no McNemar power or
sample-size function (its ``stats.power`` classes are t, F, chi-square and normal tests of
independent samples), so Connor's formula would be ours either way, and its ``multipletests``
would bring statsmodels and patsy into every install (the lock, the images) for Holm's method,
which is the cumulative maximum below. Both are tested against published worked examples.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

# scipy.special, as in aggregate: scipy.stats costs seconds of import in every report
from scipy.special import ndtr, ndtri

ALPHA = 0.05  # two-sided
POWER = 0.80


def _z_alpha(alpha: float) -> float:
    """z_{1-alpha/2}, the two-sided critical value, after checking the level."""
    if not 0.0 < alpha < 1.0:
        raise ValueError(f"alpha must lie in (0, 1), got {alpha}")
    return float(ndtri(1.0 - alpha / 2.0))


def _quantiles(alpha: float, power: float) -> tuple[float, float]:
    """(z_{1-alpha/2}, z_{power}) after checking the levels (power above 1/2: the formulas
    below take the root that belongs to it)."""
    if not 0.5 < power < 1.0:
        raise ValueError(f"power must lie in (0.5, 1), got {power}")
    return _z_alpha(alpha), float(ndtri(power))


def _check_rates(discordance: float, effect: float = 0.0) -> None:
    if not 0.0 <= discordance <= 1.0:
        raise ValueError(
            f"discordance (share of discordant pairs) must lie in [0, 1], got {discordance}"
        )
    if not -1.0 <= effect <= 1.0:
        raise ValueError(f"effect (difference in success rates) must lie in [-1, 1], got {effect}")


def mcnemar_power(n_pairs: float, discordance: float, effect: float, alpha: float = ALPHA) -> float:
    """Power of McNemar's two-sided test on ``n_pairs`` pairs with a share ``discordance`` of
    discordant pairs against a difference ``effect`` in success rates (Connor 1987, both tails).

    No discordant pairs: 0 (the test has nothing to count). A difference larger than the
    discordance is impossible (|p10 - p01| <= p10 + p01): ValueError."""
    z_a = _z_alpha(alpha)
    _check_rates(discordance, effect)
    if n_pairs < 0:
        raise ValueError(f"n_pairs must be >= 0, got {n_pairs}")
    d, psi = abs(effect), discordance
    if d > psi:
        raise ValueError(
            f"a difference of {d:g} needs a share of at least {d:g} discordant pairs, got {psi:g}"
        )
    if psi == 0.0:
        return 0.0
    sd = math.sqrt(max(psi - d * d, 0.0))
    shift, crit = d * math.sqrt(n_pairs), z_a * math.sqrt(psi)
    if sd == 0.0:  # every pair discordant and all one way: the statistic is deterministic
        return 1.0 if shift > crit else 0.0
    return float(ndtr((shift - crit) / sd) + ndtr((-shift - crit) / sd))


def pairs_needed(
    effect: float, discordance: float, alpha: float = ALPHA, power: float = POWER
) -> float:
    """Pairs a paired comparison needs to detect a difference ``effect`` in success rates with
    McNemar's two-sided test at level ``alpha`` with probability ``power``, when a share
    ``discordance`` of its pairs are discordant: Connor's (1987) n, rounded up.

    ``math.inf`` where no number of pairs will do at that discordance: no difference
    (``effect`` 0), no discordant pairs, or a difference larger than the discordance
    (a difference d needs a share of at least d discordant pairs)."""
    z_a, z_b = _quantiles(alpha, power)
    _check_rates(discordance, effect)
    d, psi = abs(effect), discordance
    if d == 0.0 or psi == 0.0 or d > psi:
        return math.inf
    n = ((z_a * math.sqrt(psi) + z_b * math.sqrt(psi - d * d)) / d) ** 2
    return float(math.ceil(n - 1e-9))  # not 23 pairs for an n that is 22 by rounding error


def minimum_detectable_effect(
    n_pairs: float, discordance: float, alpha: float = ALPHA, power: float = POWER
) -> float:
    """The smallest difference in success rates (a proportion, 0.05 = 5 pp) that McNemar's
    two-sided test at level ``alpha`` detects with probability ``power`` on ``n_pairs`` pairs
    of which a share ``discordance`` is discordant: Connor's (1987) n solved for the difference,

        delta = (z_a sqrt(psi n) + z_b sqrt(psi (n + z_b^2 - z_a^2))) / (n + z_b^2)

    (the root of (n + z_b^2) delta^2 - 2 z_a sqrt(psi n) delta + psi (z_a^2 - z_b^2) = 0 with
    sqrt(n) delta >= z_a sqrt(psi)), so ``pairs_needed(minimum_detectable_effect(n, psi), psi)``
    is n again.

    ``math.inf`` where no difference is detectable: no pairs, no discordant pairs, too few pairs
    for the normal approximation to reach ``power`` at all (n <= z_a^2 - z_b^2, about 3.1), or
    a root above the discordance (even with every discordant pair going one way, the power stays
    below ``power``)."""
    z_a, z_b = _quantiles(alpha, power)
    _check_rates(discordance)
    if n_pairs < 0:
        raise ValueError(f"n_pairs must be >= 0, got {n_pairs}")
    psi = discordance
    if n_pairs == 0 or psi == 0.0:
        return math.inf
    under_root = psi * (n_pairs + z_b * z_b - z_a * z_a)
    if under_root <= 0.0:
        return math.inf
    delta = (z_a * math.sqrt(psi * n_pairs) + z_b * math.sqrt(under_root)) / (n_pairs + z_b * z_b)
    return math.inf if delta > psi else float(delta)


@dataclass(frozen=True)
class PairedPower:
    """What one paired comparison could detect (McNemar, Connor 1987), from its own counts."""

    n_pairs: int
    discordant: int  # pairs whose two outcomes differ (only the cell + only the baseline)
    discordance: float  # discordant / n_pairs; nan without pairs
    mde: float  # minimum detectable |difference| (a proportion); inf where none is detectable
    pairs_for_1pp: float  # pairs needed for a 1 pp difference at this discordance; inf, or nan
    pairs_for_5pp: float  # ... for a 5 pp difference
    alpha: float
    power: float
    note: str  # why a figure is inf or nan; "" when all are finite

    @property
    def mde_pp(self) -> float:
        """The minimum detectable effect in percentage points."""
        return 100.0 * self.mde


def _pct(x: float) -> str:
    return f"{100.0 * x:.3g}%"


def paired_power(
    n_pairs: int, discordant: int, alpha: float = ALPHA, power: float = POWER
) -> PairedPower:
    """The minimum detectable effect of a paired comparison of ``n_pairs`` pairs, ``discordant``
    of them discordant, and the pairs it would need for 1 pp and 5 pp at its discordance rate,
    each with the reason where it is undefined (``note``)."""
    if not 0 <= discordant <= n_pairs:
        raise ValueError(f"need 0 <= discordant <= n_pairs, got {discordant} of {n_pairs}")
    _quantiles(alpha, power)
    level = f"{100 * power:.0f}% power"
    if n_pairs == 0:
        return PairedPower(
            0,
            0,
            math.nan,
            math.inf,
            math.nan,
            math.nan,
            alpha,
            power,
            "no pairs: nothing is detectable, and there is no discordance rate to plan pairs from",
        )
    psi = discordant / n_pairs
    mde = minimum_detectable_effect(n_pairs, psi, alpha, power)
    need = {pp: pairs_needed(pp / 100.0, psi, alpha, power) for pp in (1, 5)}
    notes = []
    if discordant == 0:
        notes.append(
            f"no discordant pairs in {n_pairs}: McNemar's test counts only pairs whose outcomes "
            "differ, so no difference is detectable and more pairs at a 0% discordance rate "
            "would not help"
        )
    else:
        if math.isinf(mde):
            notes.append(
                f"no difference is detectable at {level}: even with all {discordant} discordant "
                f"pairs of {n_pairs} going one way (a {100 * psi:.3g} pp difference), the power "
                f"stays below {100 * power:.0f}%"
            )
        for pp, n in need.items():
            if math.isinf(n):
                notes.append(
                    f"a {pp} pp difference needs at least {pp}% discordant pairs; "
                    f"this comparison has {_pct(psi)}"
                )
    return PairedPower(
        n_pairs, discordant, psi, mde, need[1], need[5], alpha, power, "; ".join(notes)
    )


def holm(p_values: Sequence[float] | np.ndarray) -> np.ndarray:
    """Holm's (1979) step-down adjusted p-values, in the order given.

    With the m p-values sorted, p_(1) <= ... <= p_(m), the adjusted p_(i) is
    max_{j <= i} min(1, (m - j + 1) p_(j)): a test is rejected at family-wise level alpha
    exactly where Holm's procedure rejects it, its adjusted p-value is at least its raw one,
    and the adjusted values keep the raw values' order (ties stay tied). NaN entries stay NaN
    and do not count in m, as in R's ``p.adjust``."""
    p = np.asarray(p_values, dtype=float)
    if p.ndim != 1:
        raise ValueError(f"p_values must be one-dimensional, got shape {p.shape}")
    known = ~np.isnan(p)
    if np.any((p[known] < 0.0) | (p[known] > 1.0)):
        raise ValueError(f"p-values must lie in [0, 1], got {p[known].min()}..{p[known].max()}")
    out = np.full(p.shape, np.nan)
    idx = np.flatnonzero(known)
    m = idx.size
    if m == 0:
        return out
    order = np.argsort(p[idx], kind="stable")
    scaled = (m - np.arange(m)) * p[idx][order]
    out[idx[order]] = np.minimum(np.maximum.accumulate(scaled), 1.0)
    return out
