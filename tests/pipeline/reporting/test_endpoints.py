"""A study's report: its declared endpoints with Holm's correction, every other comparison
exploratory; a member with tau: calibrated fits it on its held-out episodes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from scipy.stats import binomtest

from pipeline import cli
from pipeline.reporting.run_data import load_run
from pipeline.results.calibration import read_calibration

CONF = Path(__file__).resolve().parents[3] / "conf"
SMOKE = CONF / "smoke.yaml"
COMMON = "executor.kind=inline, executor.workers=1, tracking.enabled=false"


def _mcnemar(run_dir: Path, cell: str, reference: str) -> tuple[float, int]:
    """Exact McNemar p of ``cell`` against ``reference`` from the run's episodes, by hand."""
    eps = load_run(run_dir).episodes
    key = ["task_id", "episode_index"]
    a = eps[eps.cell_id == cell].set_index(key)["success"].astype(int)
    b = eps[eps.cell_id == reference].set_index(key)["success"].astype(int)
    d = (a - b.reindex(a.index)).to_numpy()
    only_a, only_b = int((d == 1).sum()), int((d == -1).sum())
    p = 1.0 if only_a + only_b == 0 else binomtest(only_a, only_a + only_b).pvalue
    return float(p), len(d)


def test_a_study_reports_its_primary_endpoints_with_holm_and_the_rest_exploratory(
    tmp_path: Path,
) -> None:
    study = tmp_path / "study.yaml"
    study.write_text(
        f"""
name: declared
set: [episodes_per_task=6, "grid=[{{mode: [diagnose, E, F]}}]", {COMMON},
      "backbone.params.noise_std=0.3"]
runs:
  - {{arch: strong, env: fake, config: {SMOKE},
     set: [idr.tau=calibrated, "calibration={{episodes_per_task: 10}}", idr.alpha=1.0]}}
  - {{arch: weak, env: fake, config: {SMOKE}, set: [backbone.params.gain=1.0, idr.alpha=1.0]}}
endpoints:
  primary:
    - {{member: strong@fake, compare: [F, diagnose]}}
    - {{member: weak@fake, compare: [E, diagnose]}}
"""
    )
    out = tmp_path / "obs"
    assert cli.main(["study", str(study), "--out", str(out)]) == 0
    result = json.loads((out / "observations.json").read_text())
    primary = result["comparisons"]["primary"]
    assert [(r["member"], r["cell"], r["reference"]) for r in primary] == [
        ("strong@fake", "F", "diagnose"),
        ("weak@fake", "E", "diagnose"),
    ]
    raw = []
    for r in primary:
        p, n = _mcnemar(out / r["member"], r["cell"], r["reference"])
        assert r["p"] == pytest.approx(p) and r["n_pairs"] == n == 12
        raw.append(p)
    # Holm over two tests: the smaller p doubled, the larger at least that, both capped at 1
    lo, hi = sorted(range(2), key=lambda i: raw[i])
    assert primary[lo]["p_holm"] == pytest.approx(min(1.0, 2 * raw[lo]))
    assert primary[hi]["p_holm"] == pytest.approx(min(1.0, max(2 * raw[lo], raw[hi])))
    assert all(r["p_holm"] >= r["p"] for r in primary)
    # every other comparison, exploratory: E vs diagnose in strong, F vs diagnose in weak
    exploratory = {(r["member"], r["cell"]) for r in result["comparisons"]["exploratory"]}
    assert exploratory == {("strong@fake", "E"), ("weak@fake", "F")}

    md = (out / "observations.md").read_text()
    primary_md = md.split("## Primary endpoints", 1)[1].split("## Exploratory comparisons")[0]
    assert "Holm" in primary_md and "| strong@fake | F vs diagnose | all |" in primary_md
    pinned = json.loads((out / "endpoints.json").read_text())["hash"]
    assert f"hash {pinned[:12]}" in primary_md
    for r in primary:
        assert f"| {r['p_holm']:.3g} | 12 |" in primary_md
    exploratory_md = md.split("## Exploratory comparisons", 1)[1]
    assert "uncorrected" in exploratory_md and "| weak@fake | F vs diagnose |" in exploratory_md
    assert "| strong@fake | E vs diagnose |" in exploratory_md
    assert "F vs diagnose" not in exploratory_md.split("| weak@fake |")[0]

    # the calibrated member fitted tau on its held-out episodes (10 per task, after 0..5)
    calib = read_calibration(out / "strong@fake")
    assert calib is not None and calib["fitted_on"] == "held_out"
    assert (calib["held_out"]["first_episode"], calib["held_out"]["last_episode"]) == (6, 15)
    assert set(load_run(out / "strong@fake").episodes.episode_index) == set(range(6))


def test_a_study_without_endpoints_says_every_comparison_is_exploratory(tmp_path: Path) -> None:
    from pipeline.reporting.endpoints import markdown

    lines = markdown({"primary": [], "exploratory": []}, None)
    assert "None declared" in "\n".join(lines)
    assert "## Exploratory comparisons" in lines


def test_an_endpoint_not_run_keeps_the_declared_family_size_in_holm() -> None:
    """Three declared endpoints, one not run (left out by --only): Holm over three, the missing
    one at p = 1, so each adjusted p now bounds the complete study's from above."""
    import math

    from pipeline.reporting.endpoints import family_holm
    from pipeline.results.power import holm

    ran = [{"ran": True, "p": 0.01}, {"ran": True, "p": 0.04}]
    partial = family_holm([*ran, {"ran": False, "p": math.nan}])
    assert partial[:2] == pytest.approx([0.03, 0.08]) and math.isnan(partial[2])
    for missing in (1e-6, 0.02, 0.5, 1.0):  # whatever the missing endpoint gives later
        complete = holm([0.01, 0.04, missing])
        assert all(c <= p + 1e-12 for c, p in zip(complete[:2], partial[:2], strict=True))
    # a declared endpoint that ran but has no pairs counts the same way
    assert family_holm([*ran, {"ran": True, "p": math.nan}])[:2] == pytest.approx([0.03, 0.08])
