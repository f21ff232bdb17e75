"""Reports at grid scale: a synthetic run dir of N episodes, before and after compaction.

The run dir is made from a real smoke run (its config, run.json and the schemas of its rows):
its episode rows are copied with shifted episode indices and each episode gets ``--inferences``
step rows, written as the driver writes them (batches of ``--batch`` episodes per cell, each a
pair of Parquet files). Then, each in a fresh process (peak RSS from the kernel): the
stored-keys scan a resume does, ``idr-eval report`` and ``idr-eval compare`` of two such runs;
then ``idr-eval compact`` and the same three again.

Writes ``benchmarks/results/report_scale.json``. Usage:
``python benchmarks/bench_report_scale.py [--episodes 100000] [--inferences 50]``
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.compute as pc

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).parent / "results" / "report_scale.json"
PY = sys.executable


def _timed(cmd: list[str]) -> dict[str, Any]:
    """Wall seconds and peak RSS (MB) of a command in its own process."""
    code = (
        "import resource, subprocess, sys, time, json;"
        "t=time.perf_counter(); r=subprocess.run(sys.argv[1:], capture_output=True, text=True);"
        "dt=time.perf_counter()-t;"
        "m=resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss/1024;"
        "print(json.dumps({'seconds': round(dt, 2), 'peak_mb': round(m), 'rc': r.returncode,"
        " 'err': r.stderr[-300:], 'out': r.stdout.strip().splitlines()[-1:]}))"
    )
    out = subprocess.run([PY, "-c", code, *cmd], cwd=ROOT, capture_output=True, text=True)
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if res["rc"] != 0:
        raise RuntimeError(f"{cmd}: {res['err']}")
    out_line = res.pop("out")
    del res["err"], res["rc"]
    if out_line and out_line[0].startswith("{"):
        res.update(json.loads(out_line[0]))  # what the command measured of itself
    return res


def make_run_dir(run_dir: Path, episodes: int, inferences: int, batch: int) -> dict[str, Any]:
    from pipeline.results.store import EPISODE_SCHEMA, STEP_SCHEMA, RunStore

    t0 = time.perf_counter()
    template = run_dir.parent / "template"
    subprocess.run(
        [
            PY,
            "-m",
            "pipeline.cli",
            "run",
            "conf/smoke.yaml",
            "--out",
            str(template),
            "executor.kind=inline",
            "tracking.enabled=false",
        ],
        cwd=ROOT,
        check=True,
        capture_output=True,
    )
    src = RunStore(template, read_only=True)
    eps, steps = src.episodes(), src.steps()
    run_dir.mkdir(parents=True)
    for name in ("config.yaml", "run.json"):
        shutil.copy(template / name, run_dir / name)
    cells = sorted(set(eps.column("cell_id").to_pylist()))
    per_cell = episodes // len(cells)
    writer = RunStore(run_dir)
    for cell in cells:
        e_cell = eps.filter(pc.equal(eps["cell_id"], cell))
        s_cell = steps.filter(pc.equal(steps["cell_id"], cell))
        first = s_cell.slice(0, 1)
        for start in range(0, per_cell, batch):
            n = min(batch, per_cell - start)
            idx = [i % e_cell.num_rows for i in range(start, start + n)]
            e = e_cell.take(idx).set_column(
                EPISODE_SCHEMA.get_field_index("episode_index"),
                "episode_index",
                pa.array(range(start, start + n), pa.int64()),
            )
            e = e.set_column(
                EPISODE_SCHEMA.get_field_index("task_id"), "task_id", pa.array(["reach"] * n)
            )
            s = first.take([0] * (n * inferences))
            s = s.set_column(
                STEP_SCHEMA.get_field_index("episode_index"),
                "episode_index",
                pa.array([start + i // inferences for i in range(n * inferences)], pa.int64()),
            )
            s = s.set_column(
                STEP_SCHEMA.get_field_index("inference_index"),
                "inference_index",
                pa.array([i % inferences for i in range(n * inferences)], pa.int64()),
            )
            s = s.set_column(
                STEP_SCHEMA.get_field_index("task_id"), "task_id", pa.array(["reach"] * len(s))
            )
            writer._seq += 1
            name = f"batch-{writer._seq:06d}-{os.urandom(4).hex()}.parquet"
            writer._write_atomic(s, writer.steps_dir / f"cell={cell}" / name)
            writer._write_atomic(e, writer.episodes_dir / f"cell={cell}" / name)
    files = len(list(run_dir.rglob("*.parquet")))
    return {
        "episodes": per_cell * len(cells),
        "step_rows": per_cell * len(cells) * inferences,
        "files": files,
        "make_seconds": round(time.perf_counter() - t0, 1),
    }


def measure(run_dir: Path, other: Path) -> dict[str, Any]:
    keys = (  # the scan alone, timed inside the process (imports excluded)
        "import json, sys, time; from pipeline.results.store import RunStore;"
        "t = time.perf_counter(); n = len(RunStore(sys.argv[1], read_only=True).stored_keys());"
        "print(json.dumps({'keys': n, 'scan_seconds': round(time.perf_counter() - t, 3)}))"
    )
    return {
        "key_scan": _timed([PY, "-c", keys, str(run_dir)]),
        "report": _timed([PY, "-m", "pipeline.cli", "report", str(run_dir)]),
        "compare": _timed(
            [
                PY,
                "-m",
                "pipeline.cli",
                "compare",
                str(run_dir),
                str(other),
                "--out",
                str(run_dir.parent / "compare"),
            ]
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=100_000)
    ap.add_argument("--inferences", type=int, default=50)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as d:
        a, b = Path(d) / "a", Path(d) / "b"
        made = make_run_dir(a, args.episodes, args.inferences, args.batch)
        print("made", made, flush=True)
        shutil.copytree(a, b)
        before = measure(a, b)
        print("uncompacted", before, flush=True)
        compact = {
            "a": _timed([PY, "-m", "pipeline.cli", "compact", str(a)]),
            "b": _timed([PY, "-m", "pipeline.cli", "compact", str(b)]),
        }
        print("compact", compact, flush=True)
        after = measure(a, b)
        print("compacted", after, flush=True)
        files_after = len(list(a.rglob("*.parquet")))
    res = {
        "machine": machine_record(),
        "run_dir": {**made, "files_compacted": files_after},
        "uncompacted": before,
        "compaction": compact["a"],
        "compacted": after,
        "speedup_report": round(before["report"]["seconds"] / after["report"]["seconds"], 2),
        "targets": {"compacted_report_s": 10, "compacted_report_peak_mb": 2048, "key_scan_s": 2},
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2))
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
