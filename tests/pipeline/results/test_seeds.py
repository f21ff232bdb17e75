"""Training seeds as a random effect: the two-level bootstrap on hand-made seeds."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.results.seeds import pooled_paired, pooled_rimg, pooled_success


def _episodes(success_e: list[int], success_d: list[int], tasks: int = 2) -> pd.DataFrame:
    rows = []
    for cell, values in (("E", success_e), ("diagnose", success_d)):
        for i, s in enumerate(values):
            rows.append(
                {
                    "cell_id": cell,
                    "suite": "s",
                    "task_id": f"t{i % tasks}",
                    "episode_index": i // tasks,
                    "success": bool(s),
                    "error": None,
                }
            )
    return pd.DataFrame(rows)


def test_one_seed_is_the_episode_bootstrap_and_a_second_unlike_seed_widens_the_interval():
    rng = np.random.default_rng(0)
    good = _episodes(list(rng.random(40) < 0.9), [1] * 40)
    bad = _episodes(list(rng.random(40) < 0.1), [1] * 40)
    one = pooled_success({0: good}, "E")
    assert one.seeds == 1 and one.value == pytest.approx(
        good.query("cell_id == 'E'").success.mean()
    )
    assert one.ci95[1] - one.ci95[0] < 0.25  # episodes alone: a narrow interval
    two = pooled_success({0: good, 1: bad}, "E")
    assert two.seeds == 2 and two.value == pytest.approx(np.mean(list(two.per_seed.values())))
    # resampling seeds: {good, good}, {good, bad}, {bad, bad} -> the interval spans both seeds
    assert two.ci95[0] < 0.2 and two.ci95[1] > 0.8
    # pooling the 80 episodes as one sample would have claimed a narrow interval
    assert two.ci95[1] - two.ci95[0] > 3 * (one.ci95[1] - one.ci95[0])


def test_a_paired_effect_two_seeds_agree_on_is_significant_one_they_split_on_is_not():
    plus = _episodes([1] * 20 + [0] * 20, [0] * 20 + [0] * 20)  # E +50 pp
    minus = _episodes([0] * 40, [1] * 20 + [0] * 20)  # E -50 pp
    agree = pooled_paired({0: plus, 1: plus, 2: plus}, "E", "diagnose")
    assert agree.value == pytest.approx(0.5) and agree.p < 0.01 and agree.ci95[0] > 0.3
    split = pooled_paired({0: plus, 1: minus}, "E", "diagnose")
    assert split.value == pytest.approx(0.0) and split.p > 0.5
    assert split.ci95[0] < -0.4 and split.ci95[1] > 0.4
    assert split.units == 80 and split.record()["per_seed"] == {"0": 0.5, "1": -0.5}


def test_rimg_per_seed_is_the_ratio_of_mean_effects_and_pooled_is_their_mean():
    def steps(e_img: float, e_prop: float) -> pd.DataFrame:
        rng = np.random.default_rng(1)
        n = 60
        return pd.DataFrame(
            {
                "task_id": [f"t{i % 3}" for i in range(n)],
                "episode_index": [i // 3 for i in range(n)],
                "e_img": e_img * (1 + 0.1 * rng.standard_normal(n)),
                "e_prop": np.full(n, e_prop),
            }
        )

    a, b = steps(1.0, 1.0), steps(3.0, 1.0)
    pooled = pooled_rimg({0: a, 1: b})
    want = [x.e_img.sum() / (x.e_img.sum() + x.e_prop.sum() + 1e-6) for x in (a, b)]
    assert list(pooled.per_seed.values()) == pytest.approx(want)
    assert pooled.value == pytest.approx(np.mean(want))
    assert pooled.ci95[0] < want[0] + 0.02 and pooled.ci95[1] > want[1] - 0.02
