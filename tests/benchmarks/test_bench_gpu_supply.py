"""The GPU supply benchmark cannot rot: its dry mode runs the same code paths on the CPU at toy
sizes (lerobot's pi0 classes, eager and through torch.compile, the idr plugin's per-chunk
latency) and writes the JSON a device run writes; unknown models are skipped with the reason."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _dry(tmp_path: Path, *args: str) -> dict:
    """The benchmark's dry run with ``args``; its JSON."""
    out = tmp_path / "supply.json"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_gpu_supply.py"), "--dry", *args]
    run = subprocess.run(
        [*cmd, "--out", str(out)], cwd=tmp_path, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-3000:]
    return json.loads(out.read_text())


@pytest.mark.slow
def test_dry_run_writes_the_supply_json(tmp_path) -> None:
    r = _dry(tmp_path, "--models", "pi0,smolvla,not_a_model")
    assert r["dry"] and r["batches"] == [1, 2] and r["actions_per_inference"] == [5, 10]
    pi0 = r["models"]["pi0"]
    for mode, sizes in (("eager", ["1", "2"]), ("compiled", ["1"])):
        assert list(pi0[mode]["per_batch"]) == sizes, mode
        for b, row in pi0[mode]["per_batch"].items():
            base, idr = row["base"], row["idr"]
            assert idr["rows_per_forward"] == 3 * base["rows_per_forward"] == 3 * int(b)
            assert base["mu_inf_per_s"] == pytest.approx(int(b) / (base["ms"] / 1e3))
            assert idr["env_steps_per_s"]["10"] == pytest.approx(10 * idr["mu_inf_per_s"])
            assert row["idr_vs_base"] == pytest.approx(idr["ms"] / base["ms"])
    assert pi0["compiled"]["compile_mode"] == "eager" and pi0["compiled"]["compile_s"] > 0
    assert "SmolVLM2's config and processor files" in r["models"]["smolvla"]["skipped"]
    assert "unknown model 'not_a_model'" in r["models"]["not_a_model"]["skipped"]
    plugin = r["plugin_latency_B1"]
    # a ratio of two timings: its value is the benchmark's to report, not a test's to assert
    # (two processes on two cores can make either side slower)
    assert plugin["E"]["ms"] > 0 and plugin["baseline"]["ms"] > 0
    assert plugin["idr_vs_base"] == pytest.approx(plugin["E"]["ms"] / plugin["baseline"]["ms"])


def test_a_spent_budget_starts_nothing_and_says_so(tmp_path) -> None:
    """A device lease ends at a fixed time: past ``--budget-s`` no model or mode is started, and
    each is recorded as skipped with that reason rather than missing from the JSON."""
    r = _dry(tmp_path, "--models", "pi0,pi05", "--budget-s", "0")
    for name in ("pi0", "pi05"):
        for mode in ("eager", "compiled"):
            assert r["models"][name][mode] == {"skipped": "not started: --budget-s 0 s spent"}
    assert r["plugin_latency_B1"]["skipped"].endswith("--budget-s 0 s spent")


def test_a_dry_run_without_out_leaves_the_committed_results_alone(tmp_path) -> None:
    """Toy CPU figures never replace the device's measurement: without ``--out`` a dry run
    writes to a new folder of the temporary directory, and says where."""
    committed = ROOT / "benchmarks" / "results" / "gpu_supply.json"
    before = committed.read_bytes()
    tmp = tmp_path / "tmp"
    tmp.mkdir()
    cmd = [sys.executable, str(ROOT / "benchmarks" / "bench_gpu_supply.py"), "--dry"]
    run = subprocess.run(
        [*cmd, "--models", "pi0", "--budget-s", "0"],  # nothing started: seconds
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "TMPDIR": str(tmp)},
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert committed.read_bytes() == before
    [written] = tmp.rglob("gpu_supply.json")
    assert f"written to {written}" in run.stdout
    assert json.loads(written.read_text())["dry"] is True
