"""lerobot-idr-wrap and lerobot-idr-calibrate: the folder appears whole or not at all, and every
bad input is one error line with exit code 2 before anything is written."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from lerobot_policy_idr.calibrate import main as calibrate_main
from lerobot_policy_idr.configuration_idr import IDRConfigError
from lerobot_policy_idr.wrap import main as wrap_main

from tests.lerobot_policy_idr.conftest import load, make_idr, obs_batch

pytestmark = pytest.mark.slow


def _refused(capsys, argv: list[str], match: str) -> str:
    assert wrap_main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and match in err, err
    return err


def test_bad_wraps_are_refused_and_create_nothing(bases, tmp_path, capsys) -> None:
    out = tmp_path / "out"
    _refused(capsys, [str(tmp_path / "none"), str(out), "--tau", "3"], "does not exist")
    _refused(capsys, [str(bases["act"]), str(out)], "needs policy.tau")
    _refused(capsys, [str(bases["act"]), str(out), "--tau", "3", "--strategy", "blur"], "blur")
    idr = make_idr(bases["act"], tmp_path / "idr", "--tau", "3")
    _refused(capsys, [str(idr), str(out), "--tau", "3"], "base type 'idr' is refused")
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no temp dirs
    _refused(capsys, [str(bases["act"]), str(idr), "--tau", "3"], "exists and is not empty")


def test_a_bundled_folder_loads_without_the_original_base(bases, tmp_path) -> None:
    base = tmp_path / "base_copy"
    shutil.copytree(bases["act"], base)
    folder = make_idr(base, tmp_path / "idr", "--tau", "3", "--bundle")
    shutil.rmtree(base)
    assert json.loads((folder / "config.json").read_text())["base_policy_path"] == "base"
    moved = shutil.move(folder, tmp_path / "moved")  # relative to the folder, wherever it is
    policy, pre, _ = load(moved)
    assert policy.predict_action_chunk(pre(obs_batch(1))).shape == (1, 4, 7)


def test_changed_base_weights_are_refused_at_load(bases, tmp_path) -> None:
    base = tmp_path / "base_copy"
    shutil.copytree(bases["act"], base)
    folder = make_idr(base, tmp_path / "idr", "--tau", "3")
    other = tmp_path / "other"
    shutil.copytree(bases["diffusion"], other)
    shutil.copy(other / "model.safetensors", base / "model.safetensors")
    with pytest.raises(IDRConfigError, match=r"changed since the IDR folder was made"):
        load(folder)


def test_calibrate_sets_tau_to_the_mean_e_img_of_diagnose_rollouts(bases, tmp_path, capsys) -> None:
    from idr_core.sidecar import read_sidecar

    folder = make_idr(
        bases["act"],
        tmp_path / "idr",
        "--mode",
        "diagnose",
        "--diagnostics-dir",
        str(tmp_path / "d"),
    )
    policy, pre, _ = load(folder)
    for seed in range(3):
        policy.reset()
        policy.predict_action_chunk(pre(obs_batch(2, seed=seed)))
    policy.sidecar.flush()
    want = float(read_sidecar(tmp_path / "d")["e_img"].mean())
    assert calibrate_main([str(folder), str(tmp_path / "d"), "--mode", "E"]) == 0
    cfg = json.loads((folder / "config.json").read_text())
    assert cfg["tau"] == pytest.approx(want, rel=1e-12) and cfg["mode"] == "E"
    assert f"{want:.6g}" in capsys.readouterr().out
    refined, _, _ = load(folder)  # the calibrated folder loads in a refining mode
    assert refined.refiner_cfg.tau == pytest.approx(want)
    # the other calibrated forms: the statistic idr-eval's tau computes (idr_core.calibration)
    e_img = read_sidecar(tmp_path / "d")["e_img"].to_numpy()
    assert calibrate_main([str(folder), str(tmp_path / "d"), "--rule", "calibrated_q90*0.5"]) == 0
    cfg = json.loads((folder / "config.json").read_text())
    assert cfg["tau"] == pytest.approx(0.5 * float(np.percentile(e_img, 90)), rel=1e-12)
    # baseline rows carry no E_img: refused, config untouched
    base_folder = make_idr(
        bases["act"],
        tmp_path / "b",
        "--mode",
        "baseline",
        "--diagnostics-dir",
        str(tmp_path / "db"),
    )
    p, pre_b, post_b = load(base_folder)
    post_b(p.select_action(pre_b(obs_batch(1))))
    p.sidecar.flush()
    assert calibrate_main([str(base_folder), str(tmp_path / "db")]) == 2
    assert "no rows of mode 'diagnose'" in capsys.readouterr().err
    assert json.loads((base_folder / "config.json").read_text())["tau"] is None
