"""The portable numerics mode across machines: the default slice run here under it must give
the committed reference's tables (benchmarks/results/portable_numerics.json) on every machine
listed as holding, over the columns the reference hashed (a column added to the schema since
does not void it). The test runs the reference's diagnose cell on two of its tasks (its
episodes' seeds depend on the task and episode index only, so they are the reference's own
episodes): the tiny VLA's three forwards per inference, on a plain and a shifted camera; the
whole slice is ``bench_portable.py --reference``'s. On a machine not listed as holding it
cannot fail, so it skips before the run and says how to check that machine:
``python benchmarks/bench_portable.py --reference`` (the docs render the list)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[3]
REFERENCE = ROOT / "benchmarks" / "results" / "portable_numerics.json"

pytestmark = [pytest.mark.sim, pytest.mark.slow]

#: the reference's diagnose cell on two of its six tasks: 6 of its 36 episodes (the whole
#: slice, with organize's 1,000-step budget and the calibrated E cell, took 197 s on the
#: AMD EPYC the reference was measured on)
SLICE = ["grid=[{mode: [diagnose]}]", "env.tasks=[pick_color, pick_color@camera_shift:0.16]"]


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
    cmd += [*ref["overrides"], *SLICE, "executor.workers=1", "executor.numerics_mode=portable"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1500)
    assert done.returncode == 0, done.stderr[-3000:]
    ours = episode_hashes(out, ref["columns"])
    assert len(ours) == 6 and set(ours) <= set(ref["hashes"])
    diff = first_difference(ours, {key: ref["hashes"][key] for key in ours})
    assert diff is None, f"{here[0]} ({here[1]}) is listed as holding, but {diff}"
