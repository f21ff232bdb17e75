"""Aggregates against small hand-computed tables."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from pipeline.results import aggregate as agg


def _wilson_by_hand(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return centre - half, centre + half


@pytest.mark.parametrize(("k", "n"), [(0, 10), (3, 3), (7, 20), (50, 50)])
def test_wilson_matches_formula(k, n) -> None:
    assert agg.wilson(k, n) == pytest.approx(_wilson_by_hand(k, n), abs=1e-9)


def test_wilson_and_mcnemar_equal_scipy_stats_binomtest() -> None:
    from scipy.stats import binomtest

    for n in (1, 2, 7, 50, 500):
        for k in sorted({0, 1, n // 3, n // 2, n - 1, n}):
            ci = binomtest(k, n).proportion_ci(method="wilson")
            assert agg.wilson(k, n) == pytest.approx((ci.low, ci.high), abs=1e-12)
    for b in range(0, 40, 3):
        for c in range(0, 40, 5):
            want = binomtest(b, b + c, 0.5).pvalue if b + c else 1.0
            assert agg.mcnemar_exact(b, c) == pytest.approx(want, rel=1e-9, abs=1e-15)


def test_mcnemar_exact_by_hand() -> None:
    assert agg.mcnemar_exact(5, 0) == pytest.approx(2 * 0.5**5)  # 0.0625
    assert agg.mcnemar_exact(3, 3) == pytest.approx(1.0)
    # b=1, c=6: two-sided = 2 * P(X <= 1), X ~ Bin(7, .5) = 2 * 8/128
    assert agg.mcnemar_exact(1, 6) == pytest.approx(16 / 128)
    assert agg.mcnemar_exact(0, 0) == 1.0


def _episodes() -> pd.DataFrame:
    rows = []
    # baseline: success on episodes 0,1 of task a; E: success on 0,1,2,3 of task a
    for cell, wins in (("baseline", {0, 1}), ("E", {0, 1, 2, 3})):
        for i in range(5):
            rows.append(
                {
                    "cell_id": cell,
                    "suite": "s",
                    "task_id": "a",
                    "episode_index": i,
                    "success": i in wins,
                    "error": None,
                    "subtasks_total": 1,
                    "subtasks_done": int(i in wins),
                    "sim_seconds": 2.0 + i,
                    "wall_seconds": 1.0,
                    "inference_ms_mean": 3.0,
                    "gate_rate": 0.5,
                    "e_img_mean": 1.0,
                    "e_prop_mean": 1.0,
                    "r_img_mean": 0.5,
                }
            )
    # a chain task: subtasks done 0, 2, 5 of 5; and one error row, excluded everywhere
    for i, done in enumerate([0, 2, 5]):
        rows.append(
            {
                "cell_id": "E",
                "suite": "s",
                "task_id": "chain",
                "episode_index": i,
                "success": done == 5,
                "error": None,
                "subtasks_total": 5,
                "subtasks_done": done,
                "sim_seconds": 9.0,
                "wall_seconds": 1.0,
                "inference_ms_mean": 3.0,
                "gate_rate": 0.5,
                "e_img_mean": 1.0,
                "e_prop_mean": 1.0,
                "r_img_mean": 0.5,
            }
        )
    rows.append(
        {**rows[-1], "episode_index": 3, "success": False, "error": "boom", "subtasks_done": 0}
    )
    return pd.DataFrame(rows)


def test_success_tables_exclude_errors() -> None:
    t = agg.success_by_task(_episodes()).set_index(["cell_id", "task_id"])
    assert t.loc[("E", "a"), "success_rate"] == pytest.approx(4 / 5)
    assert t.loc[("E", "chain"), ["n", "successes", "errors"]].tolist() == [3, 1, 1]
    lo, hi = _wilson_by_hand(4, 5)
    assert t.loc[("E", "a"), "ci_low"] == pytest.approx(lo) and t.loc[
        ("E", "a"), "ci_high"
    ] == pytest.approx(hi)
    o = agg.success_overall(_episodes()).set_index("cell_id")
    assert o.loc["E", "success_rate"] == pytest.approx(5 / 8) and o.loc["E", "errors"] == 1


def test_chain_rates_and_avg_len() -> None:
    c = agg.chain_metrics(_episodes()).iloc[0]
    assert c["avg_len"] == pytest.approx(7 / 3)
    assert [c[f"rate_{i}of5"] for i in range(1, 6)] == pytest.approx(
        [2 / 3, 2 / 3, 1 / 3, 1 / 3, 1 / 3]
    )
    assert c["avg_len_low"] <= c["avg_len"] <= c["avg_len_high"]


def test_paired_difference_on_shared_keys() -> None:
    (d,) = agg.paired_vs_baseline(_episodes())
    # shared keys: task a, episodes 0..4; E wins 2 more, baseline none more
    assert (d.cell_id, d.n_pairs, d.only_cell, d.only_baseline) == ("E", 5, 2, 0)
    assert d.diff == pytest.approx(0.4)
    assert d.p_value == pytest.approx(0.5)  # 2 * 0.5**2
    assert d.ci_low <= 0.4 <= d.ci_high


def test_paired_difference_says_what_it_could_detect() -> None:
    # 5 pairs, 2 discordant: even both one way (40 pp) is below 80% power; planning pairs at
    # its 40% discordance rate (Connor 1987, see test_power) needs 31,394 for 1 pp, 1,254 for 5
    (d,) = agg.paired_vs_baseline(_episodes())
    assert math.isinf(d.mde_pp) and (d.pairs_for_1pp, d.pairs_for_5pp) == (31394, 1254)
    assert "all 2 discordant pairs of 5" in d.power_note
    # 200 pairs on one task, 30 won only by E and 10 only by the baseline: 20% discordant
    rows = []
    for i in range(200):
        e, base = (i < 100 or i >= 170), (i < 110)
        for cell, won in (("baseline", base), ("E", e)):
            rows.append(
                {"cell_id": cell, "suite": "s", "task_id": "a", "episode_index": i}
                | {"success": won, "error": None}
            )
    (d,) = agg.paired_vs_baseline(pd.DataFrame(rows), n_boot=200)
    assert (d.n_pairs, d.only_cell, d.only_baseline) == (200, 30, 10)
    assert d.mde_pp == pytest.approx(8.8073, abs=1e-4)
    assert (d.pairs_for_1pp, d.pairs_for_5pp, d.power_note) == (15696, 626, "")


def test_completion_time_over_successes_only() -> None:
    t = agg.completion_times(_episodes()).set_index("cell_id")
    assert t.loc["baseline", "sim_seconds_to_success"] == pytest.approx(np.mean([2.0, 3.0]))


def test_steps_summary_by_hand() -> None:
    import pyarrow as pa

    steps = pa.table(
        {
            "cell_id": ["E", "E", "E", "E", "B"],
            "task_id": ["t"] * 5,
            "episode_index": [0, 0, 0, 1, 0],
            "step": [0, 5, 10, 0, 0],
            "e_img": [1.0, 2.0, 3.0, 4.0, 9.0],
            "e_prop": [1.0] * 5,
            "r_img": [0.1, 0.2, 0.3, 0.4, 0.9],
            "gate": [1.0, 0.0, 0.0, 1.0, 0.0],
        }
    )
    per_cell, per_bin = agg.steps_summary(steps, bins=2)
    e = {
        k: v[0]
        for k, v in per_cell.filter(pa.compute.equal(per_cell["cell_id"], "E")).to_pydict().items()
    }
    assert (
        e["inferences"] == 4
        and e["e_img"] == pytest.approx(2.5)
        and e["gate"] == pytest.approx(0.5)
    )
    rows = per_bin.filter(pa.compute.equal(per_bin["cell_id"], "E")).to_pylist()
    # progress: ep0 steps 0, .5, 1 -> bins 0, 1, 1; ep1 step 0 of 0 -> bin 0
    assert [(r["progress_bin"], r["e_img_mean"]) for r in rows] == [(0, 2.5), (1, 2.5)]


def test_failure_causes_count_failed_episodes_by_cause() -> None:
    df = _episodes()
    # task a: baseline fails episodes 2, 3, 4 (two timeouts, one of the env's own causes)
    fail = {(c, "a", i): "timeout" for c in ("baseline", "E") for i in range(5)}
    fail[("baseline", "a", 4)] = "wrong_order"
    df["failure"] = [
        None if s or e is not None else fail.get((c, t, i), "subtask_budget")
        for c, t, i, s, e in zip(
            df.cell_id, df.task_id, df.episode_index, df.success, df.error, strict=True
        )
    ]
    t = agg.failure_causes(df).set_index(["cell_id", "task_id"])
    assert list(t.columns[:2]) == ["n", "failed"]
    assert list(t.columns[2:]) == ["timeout", "subtask_budget", "wrong_order"]  # by frequency
    assert t.loc[("baseline", "a")].tolist() == [5, 3, 2, 0, 1]
    assert t.loc[("E", "a")].tolist() == [5, 1, 1, 0, 0]
    # chain: episodes done 0 and 2 of 5 failed; the error row is neither counted nor a failure
    assert t.loc[("E", "chain")].tolist() == [3, 2, 0, 2, 0]


def test_failure_causes_of_old_rows_are_unknown_and_all_successes_give_empty() -> None:
    df = _episodes()
    t = agg.failure_causes(df).set_index(["cell_id", "task_id"])  # no failure column at all
    assert list(t.columns) == ["n", "failed", "unknown"]
    assert t.loc[("baseline", "a"), "unknown"] == 3
    assert agg.failure_causes(df[df["success"]]).empty


def test_bootstrap_by_counts_matches_resampling_episodes() -> None:
    """Few distinct values: the multinomial draw gives the interval index resampling gives."""
    rng = np.random.default_rng(3)
    for values in (rng.binomial(1, 0.3, 300), rng.integers(0, 6, 500), rng.integers(-1, 2, 400)):
        values = values.astype(float)
        idx = np.random.default_rng(9).integers(0, values.size, size=(20000, values.size))
        want = np.quantile(values[idx].mean(axis=1), [0.025, 0.975])
        got = agg.bootstrap_mean_ci(values, n_boot=20000)
        assert got == pytest.approx(tuple(want), abs=0.01 * max(1.0, np.ptp(values)))
        assert got[0] < values.mean() < got[1]
    continuous = rng.normal(size=200)  # > 64 distinct values: index resampling
    lo, hi = agg.bootstrap_mean_ci(continuous)
    assert lo < continuous.mean() < hi and hi - lo == pytest.approx(
        2 * 1.96 * continuous.std() / np.sqrt(200), rel=0.15
    )


def test_perturbation_labels_read_the_columns_and_old_rows_their_task_ids() -> None:
    """Rows with the perturbation columns use them; rows of run dirs written before the
    columns existed (nulls) are read off their task ids; a tagged frame stays as it is."""
    df = pd.DataFrame(
        {
            "task_id": ["a@image_blur:1.5", "a", "b@image_noise:0.2", "b"],
            "perturbation": ["image_blur", "none", None, None],
            "severity": [1.5, None, None, None],
        }
    )
    labels = agg.perturbation_labels(df)
    assert labels.tolist() == ["image_blur:1.5", "none", "image_noise:0.2", "none"]
    assert agg.perturbation_labels(agg.with_perturbation(df)).tolist() == labels.tolist()
    assert agg.any_perturbed(df) and not agg.any_perturbed(df.iloc[[1, 3]])
    old = df.drop(columns=["perturbation", "severity"])
    assert agg.perturbation_labels(old).tolist() == labels.tolist()
