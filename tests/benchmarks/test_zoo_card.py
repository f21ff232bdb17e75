"""The zoo's cards report a cell's R_img as the observations study does: the same estimator on the
same run gives the same number and interval; the image-zeroed control stays out of it unless a
run holds nothing else."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest

from pipeline import cli
from tests.benchmarks import load_script

ROOT = Path(__file__).resolve().parents[2]
zoo_card = load_script(ROOT / "benchmarks" / "zoo_card.py")


def _steps(task: str, e_img: float, e_prop: float, episodes: int = 4) -> list[dict]:
    return [
        {"task_id": task, "episode_index": ep, "e_img": e_img * (1 + 0.1 * ep), "e_prop": e_prop}
        for ep in range(episodes)
        for _ in range(3)
    ]


def test_card_leaves_the_control_out_unless_it_is_all_there_is() -> None:
    mixed = pd.DataFrame(_steps("t", 1.0, 1.0) + _steps("t@image_blackout:1", 0.0, 3.0))
    eff = zoo_card.card_effects(mixed)
    seen = mixed[mixed.task_id == "t"]
    assert eff["r_img"] == pytest.approx(seen.e_img.mean() / (seen.e_img.mean() + 1.0), abs=1e-5)
    assert eff["inferences"] == len(seen)
    assert eff["r_img_ci95"][0] <= eff["r_img"] <= eff["r_img_ci95"][1]
    black = zoo_card.card_effects(mixed[mixed.task_id != "t"])
    assert black["e_img"] == 0.0 and black["r_img"] == 0.0 and black["e_prop"] == 3.0


def test_card_and_study_give_one_rimg_for_one_run(tmp_path: Path) -> None:
    study = tmp_path / "study.yaml"
    common = "executor.kind=inline, executor.workers=1, tracking.enabled=false"
    study.write_text(
        f"""
set: [episodes_per_task=3, "grid=[{{mode: [diagnose]}}]"]
runs:
  - {{arch: fake, env: fake, config: {ROOT / "conf" / "smoke.yaml"}, set: [{common}]}}
"""
    )
    out = tmp_path / "obs"
    assert cli.main(["study", str(study), "--out", str(out)]) == 0
    run = json.loads((out / "observations.json").read_text())["runs"][0]
    eff = zoo_card.diagnose_effects(out / "fake@fake")
    assert eff["r_img"] == pytest.approx(run["r_img"])
    assert eff["r_img_ci95"] == pytest.approx(run["r_img_ci95"])
    assert (eff["e_img"], eff["e_prop"]) == pytest.approx((run["e_img"], run["e_prop"]))
