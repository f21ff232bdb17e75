"""``idr-eval sidecar``: the idr policy's diagnostics read into a report, checked by value on
hand-made sidecars (outcomes from lerobot-eval's eval_info.json or from operator marks)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from idr_core.mark import mark
from idr_core.sidecar import SidecarWriter

from pipeline.cli import main
from pipeline.reporting import sidecar as sidecar_report


def _write(
    directory, episodes: int, envs: int, mode: str, t0: float = 1000.0, costs: bool = True
) -> None:
    """``episodes`` x ``envs`` with 3 inferences each, every 5 steps; wall time 1 s apart,
    each inference 100 ms waited; r_img = 0.1 * tick, gate on at tick 0 only. ``costs``: the
    rows say their 3 forward rows and 5 executed steps (a sidecar of an older policy does
    not)."""
    cost = {"pass_rows": 3, "executed_steps": 5} if costs else {}
    w = SidecarWriter(directory, flush_every=7)
    t = t0
    for e in range(episodes):
        for tick in range(3):
            t += 1.0
            w.add(
                [
                    {
                        "episode": e,
                        "tick": tick,
                        "env": i,
                        "step": 1 + 5 * tick,
                        "wall_time": t,
                        "mode": mode,
                        "forward_ms": 90.0,
                        "refine_ms": 10.0,
                        "inference_ms": 100.0,
                        "wait_ms": 100.0,
                        "e_img": 1.0,
                        "e_prop": 1.0,
                        "r_img": 0.1 * tick,
                        "gate": 1.0 if tick == 0 else 0.0,
                        "w_prop": 0.05,
                        "clipped": 1,
                        "fallback": "",
                        **cost,
                    }
                    for i in range(envs)
                ]
            )
        t += 10.0  # between episodes
    w.flush()


def test_eval_info_outcomes_and_latency_aware_completion(tmp_path) -> None:
    _write(tmp_path / "d", episodes=2, envs=2, mode="E")
    info = {"per_task": [{"metrics": {"successes": [True, False, False, True]}}]}
    (tmp_path / "eval_info.json").write_text(json.dumps(info))
    data = sidecar_report.build([tmp_path / "d"], tmp_path / "eval_info.json", 10.0, None)
    eps = data.episodes.sort_values(["episode", "env"])
    # lerobot-eval's episode e * batch + env
    assert list(eps["success"]) == [True, False, False, True]
    # 3 chunks every 5 steps: 15 steps at 10 fps + 3 waits of 100 ms
    assert np.allclose(eps["completion_s"].dropna(), [1.5 + 0.3, 1.5 + 0.3])
    table = sidecar_report.summary(data).iloc[0]
    assert table["success"] == "2/4" and table["success_rate"] == 0.5
    assert table["r_img_mean"] == pytest.approx(0.1) and table["gate_rate"] == pytest.approx(1 / 3)
    assert table["clipped"] == 12 and table["inference_ms_median"] == 100.0
    # per executed env step: 3 rows and 100 ms per inference, each inference 5 steps
    assert table["pass_rows_per_step"] == pytest.approx(0.6)
    assert table["inference_ms_per_step"] == pytest.approx(20.0)
    prog = data.rows.groupby("tick")["progress"].first()
    assert list(prog) == [0.0, 5 / 15, 10 / 15]


def test_operator_marks_give_success_and_wall_completion_time(tmp_path) -> None:
    _write(tmp_path / "d", episodes=2, envs=1, mode="E", t0=1000.0, costs=False)
    # episode 0: rows at 1001, 1002, 1003 (first request at 1000.9); episode 1 from 1014
    mark(tmp_path / "d", "success", when=1004.9)
    mark(tmp_path / "d", "failure", when=1017.0)
    data = sidecar_report.build([tmp_path / "d"], None, None, None)
    assert np.isnan(sidecar_report.summary(data).iloc[0]["pass_rows_per_step"])  # not recorded
    eps = data.episodes.sort_values("episode")
    assert list(eps["success"]) == [True, False]
    assert eps["completion_s"].iloc[0] == pytest.approx(4.0)
    assert np.isnan(eps["completion_s"].iloc[1])


def test_cli_writes_the_report_and_refuses_bad_input(tmp_path, capsys) -> None:
    _write(tmp_path / "base", 1, 1, "baseline")
    _write(tmp_path / "idr", 1, 1, "E")
    out = tmp_path / "out"
    assert main(["sidecar", str(tmp_path / "base"), str(tmp_path / "idr"), "--out", str(out)]) == 0
    text = (out / "report.md").read_text()
    assert "| baseline |" in text and "| E |" in text
    assert {p.name for p in (out / "figures").iterdir()} == {
        "inference_latency.png",
        "rimg_progress.png",
        "gate_progress.png",
    }
    assert len(pd.read_parquet(out / "episodes.parquet")) == 2
    capsys.readouterr()
    assert main(["sidecar", str(tmp_path / "nowhere"), "--out", str(out)]) == 2
    assert "is not an IDR diagnostics folder" in capsys.readouterr().err
    assert main(["sidecar", str(tmp_path / "idr"), "--out", str(out), "--fps", "0"]) == 2
    assert "--fps 0.0 must be > 0" in capsys.readouterr().err
    args = ["sidecar", str(tmp_path / "idr"), "--out", str(out), "--label", "a", "--label", "b"]
    assert main(args) == 2
    assert "--label given 2 times for 1 folders" in capsys.readouterr().err
