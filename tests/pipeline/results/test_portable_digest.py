"""The portable numerics mode across machines: the default slice run here under it must give
the committed reference's tables (benchmarks/results/portable_numerics.json) on every machine
listed as holding. On a machine not listed, the test prints the machine and the first episode
that differs and passes with a warning: add the machine to the list with
``python benchmarks/bench_portable.py --reference`` (the docs render the list)."""

from __future__ import annotations

import json
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
REFERENCE = ROOT / "benchmarks" / "results" / "portable_numerics.json"

pytestmark = [pytest.mark.sim, pytest.mark.slow]


def test_the_default_slice_under_portable_numerics_matches_the_reference(tmp_path) -> None:
    import torch

    from pipeline.results.digest import episode_hashes, first_difference
    from workers.hardware import check_portable_cpu, cpu_model

    if check_portable_cpu():
        pytest.skip(f"portable numerics need AVX2: {check_portable_cpu()}")
    ref = json.loads(REFERENCE.read_text())
    out = tmp_path / "run"
    cmd = [str(Path(sys.executable).with_name("idr-eval")), "run", ref["config"], "--out", str(out)]
    cmd += [*ref["overrides"], "executor.numerics_mode=portable"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1500)
    assert done.returncode == 0, done.stderr[-3000:]
    ours = episode_hashes(out)
    assert len(ours) == ref["episodes"]
    here = (cpu_model(), torch.backends.cpu.get_cpu_capability())
    diff = first_difference(ours, ref["hashes"])
    listed = {(m["cpu_model"], m["cpu_capability"]): m for m in ref["machines"]}
    machine = f"{here[0]} ({here[1]})"
    if here in listed and listed[here]["holds"]:
        assert diff is None, f"{machine} is listed as holding, but {diff}"
    elif diff is not None:
        print(f"portable numerics on {machine}: {diff}")
        warnings.warn(
            f"portable numerics do not hold on {machine} ({diff}); record it with "
            "python benchmarks/bench_portable.py --reference",
            stacklevel=1,
        )
    else:
        print(f"portable numerics hold on the unlisted {machine}: add it to the list")
