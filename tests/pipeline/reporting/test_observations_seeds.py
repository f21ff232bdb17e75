"""A study whose member lists training seeds: the shipped tiny VLA's two MetaWorld seeds, cut to a
few short episodes, with declared endpoints and a held-out calibration block. The report gives
each seed's figures and the member's pooled over seeds (two-level bootstrap), the primary
endpoint on the pooled difference with Holm, the exploratory rest, and minimum detectable
effects; the correlation across members takes one point per member."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pipeline import cli
from pipeline.reporting.run_data import load_run
from pipeline.results.calibration import read_calibration

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[3]
ZOO = ROOT / "checkpoints" / "zoo" / "metaworld"
SHORT = [
    "episodes_per_task=2",
    '"env.tasks=[button-press-v3]"',
    "env.params.max_steps=12",
    "executor.kind=inline",
    "executor.workers=1",
    "tracking.enabled=false",
    '"calibration={episodes_per_task: 10}"',
]


def test_a_member_with_two_training_seeds_is_reported_per_seed_and_pooled(tmp_path: Path):
    study = tmp_path / "study.yaml"
    study.write_text(
        f"""
name: seeds
set: [{", ".join(SHORT)}]
runs:
  - {{arch: tiny_vla, env: metaworld, seed: 0, config: {ROOT}/conf/zoo/metaworld.yaml,
     set: [backbone.params.path={ZOO}/tiny_vla]}}
  - {{arch: tiny_vla, env: metaworld, seed: 1, config: {ROOT}/conf/zoo/metaworld.yaml,
     set: [backbone.params.path={ZOO}/tiny_vla_seed1]}}
endpoints:
  primary:
    - {{member: tiny_vla@metaworld, compare: [E, diagnose]}}
    - {{member: "tiny_vla@metaworld:seed1", compare: [E, diagnose]}}
"""
    )
    out = tmp_path / "obs"
    assert cli.main(["study", str(study), "--out", str(out)]) == 0
    runs = {s: out / f"tiny_vla@metaworld:seed{s}" for s in (0, 1)}
    for run_dir in runs.values():  # each seed fitted tau on its own held-out episodes
        calib = read_calibration(run_dir)
        assert calib is not None and calib["fitted_on"] == "held_out"
        assert set(load_run(run_dir).episodes.episode_index) == {0, 1}
    result = json.loads((out / "observations.json").read_text())

    # per seed: each run's own figures; pooled: the mean of the seeds' figures
    per_run = {r["seed"]: r for r in result["runs"]}
    assert set(per_run) == {0, 1}
    (member,) = result["members"]
    assert member["member"] == "tiny_vla@metaworld" and member["seeds"] == [0, 1]
    rimg = member["r_img"]
    assert rimg["per_seed"] == pytest.approx({"0": per_run[0]["r_img"], "1": per_run[1]["r_img"]})
    assert rimg["value"] == pytest.approx(np.mean([per_run[0]["r_img"], per_run[1]["r_img"]]))
    assert rimg["ci95"][0] <= min(rimg["per_seed"].values()) + 1e-9
    assert rimg["ci95"][1] >= max(rimg["per_seed"].values()) - 1e-9  # seeds resampled

    # the primary endpoints: the member pooled (two-level bootstrap), one seed (McNemar), Holm
    pooled, one = result["comparisons"]["primary"]
    assert pooled["test"] == "two-level bootstrap" and pooled["seeds"] == 2
    assert pooled["n_pairs"] == 4 and set(pooled["per_seed"]) == {"0", "1"}
    assert pooled["diff"] == pytest.approx(np.mean(list(pooled["per_seed"].values())))
    assert one["test"] == "McNemar" and one["seeds"] == 1 and one["n_pairs"] == 2
    for r in (pooled, one):
        assert r["p_holm"] >= r["p"] and "mde_pp" in r
    exploratory = {(r["member"], r["cell"]) for r in result["comparisons"]["exploratory"]}
    assert exploratory == {("tiny_vla@metaworld:seed0", "E")}  # seed 1 and the pool: declared

    # one point per member in the correlation, and it says how many seeds stand behind it
    corr = result["rimg_vs_gain"]
    assert corr["members"] == ["tiny_vla@metaworld"] and corr["seeds"] == {"tiny_vla@metaworld": 2}

    md = (out / "observations.md").read_text()
    assert "## Members over their training seeds" in md and "two-level bootstrap" in md
    assert "| tiny_vla@metaworld | 2 |" in md  # the member's pooled row, with its seed count
    primary_md = md.split("## Primary endpoints", 1)[1].split("## Exploratory")[0]
    assert "| tiny_vla@metaworld | E vs diagnose | all | 2 (s0 " in primary_md
    assert "(two-level bootstrap)" in primary_md and "(McNemar)" in primary_md
    assert "MDE pp" in primary_md
    assert "one point per architecture @ environment" in md
