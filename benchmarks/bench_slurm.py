"""Slurm: what a job pays for Slurm and for starting Ray on its allocation.

A real Slurm on this machine (tests/slurmcluster.py: slurmctld, two slurmd in network
namespaces), the smoke preset submitted with ``sbatch docker/slurm.sbatch``:

1. ``sbatch`` to the first stored episode, and to the job's end, against ``idr-eval run`` of the
   same smoke on a local Ray (start of the command to its end), each ``--repeats`` times;
2. requeue to resume: ``scontrol requeue`` of a running grid to its first new stored episode.
   Slurm holds a requeued job before it may start again (its EligibleTime); that hold is
   reported on its own and then released (``scontrol update StartTime=now``), so the second
   number is what the job itself costs.

Writes ``benchmarks/results/slurm.json``. Usage: ``python benchmarks/bench_slurm.py [--repeats N]``
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
RESULTS = Path(__file__).parent / "results" / "slurm.json"
SBATCH = ROOT / "docker" / "slurm.sbatch"


def _stored(run_dir: Path) -> int:
    import pyarrow.parquet as pq

    n = 0
    for f in (run_dir / "episodes").rglob("*.parquet") if run_dir.is_dir() else []:
        try:
            n += pq.read_metadata(f).num_rows
        except Exception:  # a file being written
            continue
    return n


def _until(pred, timeout_s: float, what: str) -> float:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if pred():
            return time.monotonic()
        time.sleep(0.1)
    raise TimeoutError(what)


def _submit(sc, out: Path, log: Path, overrides: list[str]) -> str:
    """The smoke preset as a 2-node job of docker/slurm.sbatch."""
    return sc.sbatch(
        "--nodes=2",
        "--cpus-per-task=2",
        f"--output={log}",
        str(SBATCH),
        "conf/smoke.yaml",
        str(out),
        *overrides,
        cwd=ROOT,
    )


def _slurm_smoke(sc, tmp: Path, i: int) -> dict:
    out, log = tmp / f"smoke{i}", tmp / f"smoke{i}.out"
    t0 = time.monotonic()
    job = _submit(sc, out, log, [])
    first = _until(lambda: _stored(out) > 0, 300, f"no episode of job {job}")
    end = _until(lambda: sc.job(job).get("JobState") in {"COMPLETED", "FAILED"}, 300, f"job {job}")
    state = sc.job(job)["JobState"]
    assert state == "COMPLETED", log.read_text()[-2000:]
    events = [json.loads(x) for x in (out / "slurm.jsonl").read_text().splitlines()]
    ray_up = next(e["t"] for e in events if e["event"] == "ray_up") - events[0]["t"]
    return {"to_first_episode_s": first - t0, "to_end_s": end - t0, "ray_up_s": ray_up}


def _local_smoke(tmp: Path, i: int) -> dict:
    out = tmp / f"local{i}"
    t0 = time.monotonic()
    proc = subprocess.Popen(
        [
            str(Path(sys.executable).with_name("idr-eval")),
            "run",
            "conf/smoke.yaml",
            "--out",
            str(out),
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    first = _until(lambda: _stored(out) > 0, 300, "no local episode")
    assert proc.wait(timeout=300) == 0
    return {"to_first_episode_s": first - t0, "to_end_s": time.monotonic() - t0}


def _requeue(sc, tmp: Path) -> dict:
    out, log = tmp / "requeue", tmp / "requeue.out"
    job = _submit(sc, out, log, ["episodes_per_task=12", "backbone.params.delay_s=0.1"])
    _until(lambda: _stored(out) >= 4, 300, "no episodes before the requeue")
    t_requeue = time.monotonic()
    wall_requeue = time.time()
    sc.scontrol("requeue", job)
    _until(lambda: sc.job(job).get("Restarts") == "1", 120, "not requeued")
    # released once the last start has left the nodes (earlier, the new start fails: "Job
    # credential revoked")
    _until(lambda: sc.job(job).get("Reason") == "BeginTime" and sc.all_idle(), 120, "not held")
    eligible = sc.job(job).get("EligibleTime", "")  # the hold Slurm put on the requeued job
    hold = (
        datetime.fromisoformat(eligible).timestamp() - wall_requeue
        if eligible[:1].isdigit()
        else None
    )
    time.sleep(1)
    sc.scontrol("update", f"JobId={job}", "StartTime=now", check=False)
    n = _stored(out)
    resumed = _until(lambda: _stored(out) > n, 300, "no episode after the requeue")
    _until(lambda: sc.job(job).get("JobState") == "COMPLETED", 300, "requeued job did not end")
    return {"slurm_hold_s": hold, "requeue_to_resume_s": resumed - t_requeue}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()
    from slurmcluster import SlurmCluster, unavailable

    why = unavailable()
    if why:
        raise SystemExit(f"bench_slurm: {why}")
    with tempfile.TemporaryDirectory() as d, SlurmCluster(nodes=2, cpus=2, gpus=0) as sc:
        tmp = Path(d)
        slurm = [_slurm_smoke(sc, tmp, i) for i in range(args.repeats)]
        local = [_local_smoke(tmp, i) for i in range(args.repeats)]
        requeue = _requeue(sc, tmp)

    def med(rows: list[dict], key: str) -> float:
        return round(statistics.median(r[key] for r in rows), 2)

    res = {
        "what": "the smoke preset (12 episodes) under Slurm (2 slurmd in network namespaces, "
        "docker/slurm.sbatch) vs idr-eval run on a local Ray; medians of --repeats",
        "repeats": args.repeats,
        "slurm": {
            "sbatch_to_first_episode_s": med(slurm, "to_first_episode_s"),
            "sbatch_to_end_s": med(slurm, "to_end_s"),
            "ray_up_s": med(slurm, "ray_up_s"),
            "runs": slurm,
        },
        "local_ray": {
            "start_to_first_episode_s": med(local, "to_first_episode_s"),
            "start_to_end_s": med(local, "to_end_s"),
            "runs": local,
        },
        "slurm_overhead_s": round(med(slurm, "to_end_s") - med(local, "to_end_s"), 2),
        "slurm_over_local_ratio": round(med(slurm, "to_end_s") / med(local, "to_end_s"), 2),
        "requeue": {k: (round(v, 2) if v is not None else None) for k, v in requeue.items()},
        "machine": machine_record(),
    }
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(res, indent=2) + "\n")
    print(json.dumps({k: v for k, v in res.items() if k != "machine"}, indent=1))


if __name__ == "__main__":
    main()
