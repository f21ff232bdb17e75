"""The observations report: its statistics on hand-made numbers, and a study run end to end."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from pipeline import cli
from pipeline.results.observation_stats import rank_correlation, rimg_interval
from pipeline.results.store import RunStore

CONF = Path(__file__).resolve().parents[3] / "conf"


def test_rimg_is_the_ratio_of_means_with_an_episode_interval() -> None:
    rng = np.random.default_rng(0)
    rows = []
    for ep in range(20):
        for _step in range(5):
            rows.append(
                {
                    "task_id": "t",
                    "episode_index": ep,
                    "e_img": 1.0 + rng.random(),
                    "e_prop": 3.0 + rng.random(),
                }
            )
    steps = pd.DataFrame(rows)
    point, lo, hi = rimg_interval(steps)
    assert point == pytest.approx(steps.e_img.mean() / (steps.e_img.mean() + steps.e_prop.mean()))
    assert lo < point < hi and hi - lo < 0.05
    # one episode only: nothing to resample, the interval collapses
    one = steps[steps.episode_index == 0]
    p1, lo1, hi1 = rimg_interval(one)
    assert lo1 == pytest.approx(p1) and hi1 == pytest.approx(p1)


def test_rank_correlation_exact_permutation_p() -> None:
    r = rank_correlation([0.1, 0.2, 0.3, 0.4], [1.0, 2.0, 3.0, 4.0])
    assert r["rho"] == pytest.approx(1.0)
    assert r["p"] == pytest.approx(2 / 24)  # rho = +-1 in 2 of the 4! pairings
    assert r["finding"] == "inconclusive"  # 4 points cannot reach 0.05
    five = rank_correlation([1, 2, 3, 4, 5], [5, 4, 3, 2, 1])
    assert five["rho"] == pytest.approx(-1.0) and five["p"] == pytest.approx(2 / 120)
    assert five["finding"] == "negative"
    assert rank_correlation([1, 2], [1, 2])["finding"].startswith("too few")


def test_study_runs_each_member_and_reports_across_them(tmp_path: Path, capsys) -> None:
    study = tmp_path / "study.yaml"
    smoke = CONF / "smoke.yaml"
    common = "executor.kind=inline, executor.workers=1, tracking.enabled=false"
    study.write_text(
        f"""
name: two_fakes
set: [episodes_per_task=2, "grid=[{{mode: [diagnose, E]}}]"]
runs:
  - {{arch: strong, env: fake, config: {smoke}, set: [backbone.params.gain=5.0, {common}]}}
  - {{arch: weak, env: fake, config: {smoke}, set: [backbone.params.gain=1.0, {common}]}}
"""
    )
    out = tmp_path / "obs"
    assert cli.main(["study", str(study), "--out", str(out)]) == 0
    result = json.loads((out / "observations.json").read_text())
    assert [(r["arch"], r["env"]) for r in result["runs"]] == [("strong", "fake"), ("weak", "fake")]
    for r in result["runs"]:
        steps = RunStore(out / f"{r['arch']}@fake", read_only=True).steps().to_pandas()
        diag = steps[steps.cell_id == "diagnose"]
        assert r["r_img"] == pytest.approx(
            diag.e_img.mean() / (diag.e_img.mean() + diag.e_prop.mean() + 1e-6)
        )
        assert r["r_img_ci95"][0] <= r["r_img"] <= r["r_img_ci95"][1]
        assert len(r["progress"]) == 10
        assert r["gain_E"]["n_pairs"] == 4  # 2 tasks x 2 episodes
    # the gain scales E_img and E_prop alike (a = gain * (marker - state)): R_img barely moves,
    # the effects' size does
    strong, weak = result["runs"]
    assert strong["e_img"] > 3 * weak["e_img"]
    assert result["rimg_vs_gain"]["finding"].startswith("too few")
    md = (out / "observations.md").read_text()
    assert (
        "| strong | fake |" in md and (out / "figures" / "observations_rimg_heatmap.png").is_file()
    )
    # a second call resumes: every episode already stored, the same numbers
    assert cli.main(["study", str(study), "--out", str(out)]) == 0
    assert json.loads((out / "observations.json").read_text())["runs"] == result["runs"]
    # a run dir made by another code version: refused, then resumed with --allow-code-change
    meta_path = out / "weak@fake" / "run.json"
    meta = json.loads(meta_path.read_text())
    meta_path.write_text(json.dumps({**meta, "code_version": "0000000older"}))
    capsys.readouterr()
    assert cli.main(["study", str(study), "--out", str(out)]) == 2
    assert "code version 0000000older" in capsys.readouterr().err
    assert cli.main(["study", str(study), "--out", str(out), "--allow-code-change"]) == 0
    assert json.loads((out / "observations.json").read_text())["runs"] == result["runs"]


def test_a_missing_checkpoint_stops_the_study_before_any_run(tmp_path: Path, capsys) -> None:
    study = tmp_path / "study.yaml"
    study.write_text(
        f"""
runs:
  - {{arch: fake, env: fake, config: {CONF / "smoke.yaml"},
     set: [executor.kind=inline, executor.workers=1, tracking.enabled=false]}}
  - {{arch: gone, env: tabletop, config: {CONF / "zoo" / "tabletop.yaml"},
     set: ["backbone.params.path=checkpoints/zoo/nope", executor.kind=inline]}}
"""
    )
    out = tmp_path / "obs"
    assert cli.main(["study", str(study), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "gone@tabletop: " in err and "checkpoints/zoo/nope" in err
    assert "--only fake@fake" in err  # the other way on: the runs this machine can make
    assert not (out / "fake@fake" / "episodes").is_dir() or not any(
        (out / "fake@fake" / "episodes").iterdir()
    )
    # --only: the runs named, and the report across them alone
    assert cli.main(["study", str(study), "--out", str(out), "--only", "fake@fake"]) == 0
    result = json.loads((out / "observations.json").read_text())
    assert [(r["arch"], r["env"]) for r in result["runs"]] == [("fake", "fake")]
    assert not (out / "gone@tabletop").exists()


def test_rank_correlation_with_ties_matches_spearman_and_a_full_enumeration() -> None:
    import itertools

    from scipy import stats

    x = [0.35, 0.38, 0.49, 0.49, 0.54, 0.70, 0.68, 0.41]  # ties, as two runs can give
    y = [0.04, -0.02, -0.04, -0.04, -0.12, -0.10, -0.22, 0.0]
    r = rank_correlation(x, y)  # 8 points: all 40,320 pairings
    rho = stats.spearmanr(x, y).statistic
    assert r["rho"] == pytest.approx(rho)
    rx, ry = stats.rankdata(x), stats.rankdata(y)
    perms = np.array(list(itertools.permutations(ry)))  # every pairing, by brute force
    dx, dp = rx - rx.mean(), perms - perms.mean(axis=1, keepdims=True)
    every = dp @ dx / np.sqrt((dx @ dx) * (dp * dp).sum(axis=1))
    tol = 1e-12  # scipy's own two-sided p: twice the smaller tail, at most 1
    expect = min(1.0, 2 * min(np.mean(every >= rho - tol), np.mean(every <= rho + tol)))
    assert r["p"] == pytest.approx(expect, rel=1e-9)
