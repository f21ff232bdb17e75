"""The portable numerics mode across machines: the default slice run here under it must give
the committed reference's tables (benchmarks/results/portable_numerics.json) on every machine
listed as holding, over the columns the reference hashed (a column added to the schema since
does not void it). On a machine not listed as holding it cannot fail, so it skips before the
run and says how to check that machine: ``python benchmarks/bench_portable.py --reference``
(the docs render the list)."""

from __future__ import annotations

import json
import subprocess
import sys
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
    here = (cpu_model(), torch.backends.cpu.get_cpu_capability())
    listed = {(m["cpu_model"], m["cpu_capability"]): m for m in ref["machines"]}
    if not listed.get(here, {}).get("holds"):
        pytest.skip(
            f"portable numerics are not recorded as holding on {here[0]} ({here[1]}), so the "
            "reference cannot be asserted here; to check this machine and record it: "
            "python benchmarks/bench_portable.py --reference"
        )
    out = tmp_path / "run"
    cmd = [str(Path(sys.executable).with_name("idr-eval")), "run", ref["config"], "--out", str(out)]
    cmd += [*ref["overrides"], "executor.numerics_mode=portable"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1500)
    assert done.returncode == 0, done.stderr[-3000:]
    ours = episode_hashes(out, ref["columns"])
    assert len(ours) == ref["episodes"]
    diff = first_difference(ours, ref["hashes"])
    assert diff is None, f"{here[0]} ({here[1]}) is listed as holding, but {diff}"
