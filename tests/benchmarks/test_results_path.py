"""A benchmark's trial run (``--dry``, ``--quick``, ``--tiny``: toy sizes) writes to a new
temporary folder unless ``--out`` is given, never over its committed results file; every script
with such a mode goes through ``results_path``."""

from __future__ import annotations

import ast
import tempfile
from pathlib import Path

from tests.benchmarks import load_script

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS = ROOT / "benchmarks"
COMMITTED = BENCHMARKS / "results" / "gpu_supply.json"
results_path = load_script(BENCHMARKS / "results_path.py")

# the flags of a run at toy sizes, whose figures are not the machine's
TRIAL_FLAGS = ("--dry", "--quick", "--tiny", "--smoke", "--fast", "--toy")


def test_a_trial_run_without_out_writes_to_a_new_temporary_folder(
    tmp_path, monkeypatch, capsys
) -> None:
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    first = results_path.results_path(COMMITTED, None, "--dry")
    second = results_path.results_path(COMMITTED, None, "--dry")
    assert first.name == second.name == "gpu_supply.json"
    assert first.parent != second.parent  # a new folder each run
    for path in (first, second):
        assert path.parent.parent == tmp_path and path.parent.is_dir()
        assert path.parent.name.startswith("gpu_supply-dry-")
        assert not path.is_relative_to(BENCHMARKS)
    assert f"--dry without --out: writing {first}" in capsys.readouterr().out


def test_out_wins_and_a_measurement_writes_the_committed_file(tmp_path) -> None:
    out = tmp_path / "mine.json"
    assert results_path.results_path(COMMITTED, out, "--dry") == out
    assert results_path.results_path(COMMITTED, out, None) == out
    assert results_path.results_path(COMMITTED, None, None) == COMMITTED


def _flags(tree: ast.AST) -> set[str]:
    """The option strings a script's argparse parser is given."""
    return {
        arg.value
        for node in ast.walk(tree)
        if isinstance(node, ast.Call)
        and isinstance(node.func, ast.Attribute)
        and node.func.attr == "add_argument"
        for arg in node.args
        if isinstance(arg, ast.Constant) and isinstance(arg.value, str)
    }


def test_every_benchmark_with_a_trial_mode_chooses_its_output_by_results_path() -> None:
    scripts = {p: ast.parse(p.read_text()) for p in sorted(BENCHMARKS.glob("*.py"))}
    trial = {p: _flags(t) & set(TRIAL_FLAGS) for p, t in scripts.items()}
    trial = {p: flags for p, flags in trial.items() if flags}
    assert len(trial) >= 4, trial  # bench_gpu_supply, bench_gpu, bench_engine, bench_cluster
    unguarded = [
        p.name
        for p in trial
        if not any(
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id == "results_path"
            for node in ast.walk(scripts[p])
        )
    ]
    assert not unguarded, unguarded
