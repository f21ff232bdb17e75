"""LIBERO-PRO's tables on hand-made episodes: pairing each perturbed task with its original at
the same cell, task index and episode index; the Δ, its interval and the pair count; the
overall; error rows and unpaired rows left out; R_img by suite and family."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from pipeline.reporting import libero_pro as report
from pipeline.results import libero_pro as lp
from workers.envs.suites.libero.pro import families


def _episodes(rows: list[tuple]) -> pd.DataFrame:
    """rows: (cell, suite, index, episode, success, e_img, error); e_prop is 1 - e_img."""
    return pd.DataFrame(
        [
            {
                "cell_id": cell,
                "suite": suite,
                "task_id": f"{suite}/{index}",
                "episode_index": ep,
                "success": success,
                "e_img_mean": r,
                "e_prop_mean": 1.0 - r,
                "error": err,
            }
            for cell, suite, index, ep, success, r, err in rows
        ]
    )


def _grid() -> pd.DataFrame:
    rows = []
    for ep in range(4):  # original: all succeed; swap: episodes 0, 1 succeed; lan: all
        for index in (0, 1):
            rows.append(("baseline", "libero_spatial", index, ep, True, 0.5, None))
            rows.append(("baseline", "libero_spatial_swap", index, ep, ep < 2, 0.2, None))
            rows.append(("baseline", "libero_spatial_lan", index, ep, True, 0.4, None))
        rows.append(("baseline", "libero_goal", 0, ep, ep % 2 == 0, 0.6, None))
        rows.append(("baseline", "libero_goal_swap", 0, ep, False, 0.1, None))
    return _episodes(rows)


def test_each_perturbed_task_is_paired_with_its_original_task_and_episode() -> None:
    tagged = lp.tag(_grid())
    t = lp.table(tagged, "baseline")
    swap = t["libero_spatial"]["swap"]
    assert (swap.n, swap.n_pairs, swap.success) == (8, 8, 0.5)
    assert swap.delta == pytest.approx(-0.5) and swap.ci_low <= -0.5 <= swap.ci_high
    assert t["libero_spatial"]["lan"].delta == 0.0 and t["libero_spatial"]["original"].delta is None
    goal = t["libero_goal"]["swap"]  # only libero_goal/0, against its own original
    assert goal.n_pairs == 4 and goal.delta == pytest.approx(-0.5)
    everything = t["all"]["swap"]  # 12 pairs: 8 spatial (-0.5 each on average) and 4 goal
    assert everything.n_pairs == 12 and everything.delta == pytest.approx(-0.5)
    assert lp.families_present(tagged) == ["original", "swap", "lan"]


def test_the_overall_is_vla_evals_mean_of_suite_by_family_rates() -> None:
    tagged = lp.tag(_grid())
    # spatial: original 1, swap 0.5, lan 1; goal: original 0.5, swap 0
    assert lp.overall(tagged, "baseline") == (pytest.approx((1 + 0.5 + 1 + 0.5 + 0) / 5), 5)
    with_mug = _episodes([("baseline", "libero_goal_with_mug", 0, 0, True, 0.1, None)])
    assert lp.overall(lp.tag(pd.concat([_grid(), with_mug])), "baseline")[1] == 5  # not counted


def test_the_overall_reproduces_the_leaderboards_published_figures() -> None:
    """vla-eval's per-suite cells for pi0, pi0.5 and OpenVLA (LIBERO-PRO paper, Tables 2-5)
    give its published overalls 54.6, 62.0 and 57.5 by this rule."""
    cells = {  # suite -> original, object, swap, lan, task (%)
        "pi0": [(92, 94, 0, 93, 0), (97, 95, 0, 97, 0), (82, 79, 0, 82, 0), (98, 94, 0, 90, 0)],
        "pi05": [(97, 97, 38, 97, 0), (98, 97, 20, 97, 1), (93, 92, 8, 93, 1), (98, 98, 17, 96, 1)],
        "openvla": [(98, 96, 0, 98, 0), (98, 97, 0, 97, 0), (93, 81, 0, 96, 0), (99, 98, 0, 98, 0)],
    }
    published = {"pi0": 54.6, "pi05": 62.0, "openvla": 57.5}
    bases = ["libero_goal", "libero_spatial", "libero_10", "libero_object"]
    for model, suites in cells.items():
        rows = [
            (model, families.suite_name(base, fam), 0, ep, ep < pct, np.nan, None)
            for base, pcts in zip(bases, suites, strict=True)
            for fam, pct in zip(lp.OVERALL_FAMILIES, pcts, strict=True)
            for ep in range(100)
        ]
        value, n = lp.overall(lp.tag(_episodes(rows)), model)
        assert n == 20 and round(100 * value, 1) == published[model]


def test_error_rows_and_unpaired_rows_are_not_counted() -> None:
    df = _grid()
    df.loc[(df.suite == "libero_spatial") & (df.episode_index == 3), "error"] = "diverged"
    t = lp.table(lp.tag(df), "baseline")
    assert t["libero_spatial"]["swap"].n_pairs == 6  # the originals of episode 3 are errors
    assert t["libero_spatial"]["swap"].n == 8
    assert t["libero_spatial"]["original"].n == 6


def test_r_img_by_suite_and_family_is_the_ratio_of_mean_effects() -> None:
    df = _grid()
    r = lp.r_img(lp.tag(df), "baseline")
    assert r["libero_spatial"] == pytest.approx({"original": 0.5, "swap": 0.2, "lan": 0.4})
    assert r["all"]["swap"] == pytest.approx((8 * 0.2 + 4 * 0.1) / 12)
    # a ratio of means, not a mean of ratios: one episode with 10x the effects weighs 10x
    df.loc[(df.suite == "libero_goal_swap") & (df.episode_index == 0), "e_img_mean"] = 1.0
    df.loc[(df.suite == "libero_goal_swap") & (df.episode_index == 0), "e_prop_mean"] = 9.0
    img, prop = (0.1 * 3 + 1.0) / 4, (0.9 * 3 + 9.0) / 4
    assert lp.r_img(lp.tag(df), "baseline")["libero_goal"]["swap"] == pytest.approx(
        img / (img + prop + lp.EPS)
    )


def test_a_run_without_perturbed_suites_has_no_section() -> None:
    plain = _episodes([("baseline", "libero_spatial", 0, 0, True, np.nan, None)])
    assert lp.tag(plain).empty and report.section(plain) == []
    other = _episodes([("baseline", "pick_color", 0, 0, True, np.nan, None)])
    assert report.section(other) == []


def test_the_report_section_prints_delta_interval_and_r_img() -> None:
    text = "\n".join(report.section(_grid()))
    assert "| libero_spatial | 100.0 (n=8) | 50.0 (n=8) Δ -50.0 [" in text
    assert "**baseline**: overall 60.0 (over 5 of 20 rates)" in text
    assert "**R_img by suite and perturbation, baseline**" in text
    assert not math.isnan(lp.overall(lp.tag(_grid()), "baseline")[0])
