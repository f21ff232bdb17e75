"""`idr-eval slurm` (pipeline/execution/slurm.py) and docker/slurm.sbatch on a real Slurm.

The cluster (tests/slurmcluster.py): Debian's slurmctld and two slurmd, each node in a network
namespace with its own address and a count-only GPU; node n2 sees a private tmpfs over one
path (a node-local disk). One grid of 48 episodes goes through everything a shared cluster does to a job, in
this order, and must end with every episode stored exactly once: ``scontrol requeue`` mid-grid,
the wall-time warning (USR1, sent with ``scancel --signal=USR1 --batch``, as Slurm sends it
``--signal=B:USR1@120`` before the limit), ``scancel`` and a resubmission, and node n2 lost
(everything in its namespace SIGKILLed) while the resubmitted job runs.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipeline.cli import main
from pipeline.errors import ConfigError
from pipeline.execution.slurm import STOP_WAIT_S, stop_wait_s
from pipeline.execution.slurm_allocation import (
    Allocation,
    check_fits,
    expand_counts,
    gres_gpus,
    kill_wait_s,
)

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from slurmcluster import SlurmCluster, unavailable

ROOT = Path(__file__).resolve().parents[3]
SBATCH = ROOT / "docker" / "slurm.sbatch"
KEY = ["cell_id", "task_id", "episode_index"]


# --- parsing and refusals, no daemons ---------------------------------------------------------
def test_per_node_counts_are_expanded() -> None:
    assert expand_counts("2(x3),1") == [2, 2, 2, 1]
    assert expand_counts("16") == [16]
    with pytest.raises(ConfigError, match="per-node count"):
        expand_counts("2(y3)")


def test_gpus_are_read_from_the_job_gres() -> None:
    assert gres_gpus("gpu:1(IDX:0)") == 1
    assert gres_gpus("gpu:a100:2(IDX:0-1),shard:4(0/4)") == 2
    assert gres_gpus("gpu:1(IDX:0),gpu:l40s:2(IDX:1-2)") == 3
    assert gres_gpus("(null)") == 0


def test_an_allocation_too_small_names_both_numbers() -> None:
    alloc = Allocation("7", ("n1", "n2"), (2, 2), (1, 0), 0)
    with pytest.raises(ConfigError) as e:
        check_fits(alloc, demand_cpus=6, demand_gpus=2)
    msg = str(e.value)
    assert "6 CPUs but the allocation has 4" in msg
    assert "2 GPUs but the allocation has 1" in msg
    assert "n2: 2 CPU, 0 GPU" in msg
    check_fits(alloc, demand_cpus=4, demand_gpus=1)  # fits exactly


def test_sqlite_on_a_network_filesystem_is_warned_about(tmp_path, monkeypatch, caplog) -> None:
    import pipeline.execution.slurm_allocation as slurm_mod

    monkeypatch.setattr(slurm_mod, "_fstype", lambda path: "nfs4")
    with caplog.at_level("WARNING", logger="idr_eval.slurm"):
        slurm_mod.warn_sqlite_on_network_fs(None, tmp_path / "run")  # the default: SQLite
    assert "nfs4" in caplog.text and "tracking server" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="idr_eval.slurm"):
        slurm_mod.warn_sqlite_on_network_fs("http://mlflow:5000", tmp_path / "run")
    assert caplog.text == ""  # a server is the advice, not a warning
    monkeypatch.setattr(slurm_mod, "_fstype", lambda path: "ext4")
    with caplog.at_level("WARNING", logger="idr_eval.slurm"):
        slurm_mod.warn_sqlite_on_network_fs(f"sqlite:///{tmp_path}/m.db", tmp_path / "run")
    assert caplog.text == ""


def test_outside_an_allocation_names_sbatch_and_salloc(tmp_path, monkeypatch, capsys) -> None:
    monkeypatch.delenv("SLURM_JOB_ID", raising=False)
    out = tmp_path / "run"
    assert main(["slurm", "conf/smoke.yaml", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "not inside a Slurm allocation" in err and "sbatch" in err and "salloc" in err
    assert not out.exists()


def test_executor_address_is_the_launchers(tmp_path, capsys) -> None:
    rc = main(["slurm", "conf/smoke.yaml", "--out", str(tmp_path / "r"), "executor.address=auto"])
    assert rc == 2
    assert "executor.address is set by `idr-eval slurm`" in capsys.readouterr().err


# --- a real Slurm ---------------------------------------------------------------------------
slurm_only = pytest.mark.skipif(bool(unavailable()), reason=str(unavailable()))


@pytest.fixture(scope="module")
def slurm(tmp_path_factory):
    private = tmp_path_factory.mktemp("node-local")
    with SlurmCluster(nodes=2, cpus=2, gpus=1, private={"n2": private}, kill_wait_s=30) as sc:
        sc.private_path = private
        yield sc


def _stored(run_dir: Path) -> list[dict]:
    rows = []
    for f in sorted((run_dir / "episodes").rglob("*.parquet")):
        try:
            rows += pq.read_table(f, columns=[*KEY, "node", "error"]).to_pylist()
        except Exception:  # a file being written
            continue
    return rows


def _wait_stored(run_dir: Path, n: int, timeout_s: float) -> float:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if len(_stored(run_dir)) >= n:
            return time.monotonic()
        time.sleep(0.2)
    raise TimeoutError(f"fewer than {n} episodes stored in {run_dir} after {timeout_s:.0f} s")


# 2 cells x 2 tasks x 12 episodes, slowed down: long enough to be stopped four times; one
# count-only GPU per node and one per actor, so Ray must place an actor on each node
GRID = ["episodes_per_task=12", "backbone.params.delay_s=0.1", "executor.gpus_per_worker=1"]
TOTAL = 48


def _submit(sc: SlurmCluster, out: Path, log: Path) -> str:
    return sc.sbatch(
        "--nodes=2",
        "--cpus-per-task=2",
        "--gres=gpu:1",
        f"--output={log}",
        str(SBATCH),
        "conf/smoke.yaml",
        str(out),
        *GRID,
        cwd=ROOT,
    )


def _wait_restarted(sc: SlurmCluster, job: str, restarts: int, timeout_s: float = 120) -> None:
    """Until the job's ``restarts``-th start is running. Slurm holds a requeued job for 120 s
    (its EligibleTime; Reason=BeginTime); the test releases it once the nodes are idle, as an
    admin can."""
    deadline = time.monotonic() + timeout_s
    info: dict[str, str] = {}
    while time.monotonic() < deadline:
        info = sc.job(job)
        if info.get("Restarts") == str(restarts):
            if info.get("JobState") == "RUNNING":
                return
            if info.get("Reason") == "BeginTime" and sc.all_idle():
                # not before the last start is gone from the nodes: a job started while its
                # old credential is being revoked fails ("Job credential revoked")
                time.sleep(1)
                sc.scontrol("update", f"JobId={job}", "StartTime=now", check=False)
        time.sleep(0.3)
    raise TimeoutError(f"job {job} not running its restart {restarts}: {info}")


@slurm_only
def test_a_run_dir_some_node_cannot_see_is_refused(slurm, tmp_path) -> None:
    out = slurm.private_path / "run"
    log = tmp_path / "job.out"
    job = _submit(slurm, out, log)
    info = slurm.wait_job(job, {"COMPLETED", "FAILED"}, 120)
    assert info["JobState"] == "FAILED"
    text = log.read_text()
    assert "node(s) ['n2'] of the allocation do not see" in text and str(out.parent) in text
    assert not out.exists()
    assert not list(out.parent.glob(".slurm-*"))  # the tokens are cleaned up


@slurm_only
def test_an_allocation_without_the_gpus_asked_for_is_refused(slurm, tmp_path) -> None:
    log = tmp_path / "job.out"
    out = tmp_path / "run"
    job = slurm.sbatch(
        "--nodes=1",
        "--cpus-per-task=2",
        f"--output={log}",
        str(SBATCH),
        "conf/smoke.yaml",
        str(out),
        "executor.gpus_per_worker=1",
        cwd=ROOT,
    )
    assert slurm.wait_job(job, {"COMPLETED", "FAILED"}, 120)["JobState"] == "FAILED"
    assert "2 GPUs but the allocation has 0" in log.read_text()
    assert not out.exists()


@slurm_only
def test_a_grid_survives_requeue_walltime_and_a_lost_node(slurm, tmp_path) -> None:
    """Requeued by an admin (TERM), then by the wall-time warning (USR1), then a node lost in
    the third start: every episode once. A requeue reruns the same command, as a user's sbatch
    line again does after a scancel (TERM without the requeue: the first stop's own path)."""
    out = tmp_path / "runs" / "grid"
    out.parent.mkdir()
    log = tmp_path / "job.out"
    try:
        job = _submit(slurm, out, log)
        _wait_stored(out, 4, 180)
        slurm.scontrol("requeue", job)  # as an admin, or a preemption with PreemptMode=REQUEUE
        _wait_restarted(slurm, job, 1)
        _wait_stored(out, len(_stored(out)) + 4, 180)
        # the wall-time warning, as --signal=B:USR1@120 sends it: a clean stop, then requeue
        subprocess.run(["scancel", "--signal=USR1", "--batch", job], env=slurm.env(), check=True)
        _wait_restarted(slurm, job, 2)
        _wait_stored(out, len(_stored(out)) + 2, 180)
        assert len(_stored(out)) <= TOTAL - 8, (
            "the grid ran out before the node loss: make it longer"
        )
        slurm.kill_node("n2")  # slurmd, its job step and its Ray node: gone without a word
        info = slurm.wait_job(job, {"COMPLETED", "FAILED", "NODE_FAIL"}, 300)
    finally:
        slurm.start_node("n2")
        slurm.wait_idle(120)
    text = log.read_text()
    assert info["JobState"] == "COMPLETED", text[-3000:]

    rows = _stored(out)
    keys = [tuple(r[k] for k in KEY) for r in rows]
    assert len(keys) == len(set(keys)) == TOTAL  # every episode, each exactly once
    assert not [r for r in rows if r["error"]]
    assert {r["node"].split("/")[0] for r in rows} == {"n1", "n2"}  # one GPU actor per node
    assert (out / "report.md").is_file() and f"{TOTAL} episodes" in (out / "report.md").read_text()
    assert (out.parent / "mlflow.db").is_file()

    events = [json.loads(line) for line in (out / "slurm.jsonl").read_text().splitlines()]
    starts = [(e["job"], e["restarts"]) for e in events if e["event"] == "start"]
    assert starts == [(job, 0), (job, 1), (job, 2)]
    assert all(e["gpus"] == [1, 1] for e in events if e["event"] == "start")
    stops = [e for e in events if e["event"] == "stop"]
    # every start leaves its stop: the driver gets a clean stop that ends before Slurm's KILL
    assert [(e["signal"], e["requeued"]) for e in stops] == [
        ("SIGTERM", False),
        ("SIGUSR1", True),
        (None, False),
    ]
    assert (stops[-1]["rc"], stops[-1]["driver_killed"]) == (0, False)
    # a driver that stopped in time exits 143 (TERM); one killed at the deadline says so
    assert all(e["rc"] == 143 for e in stops[:-1] if not e["driver_killed"])


def test_the_drivers_clean_stop_ends_before_slurms_kill() -> None:
    assert stop_wait_s(None) == STOP_WAIT_S  # KillWait unreadable: the launcher's own limit
    assert stop_wait_s(30.0) == 25.0  # Slurm's default KillWait, 5 s kept for the stop event
    assert stop_wait_s(600.0) == STOP_WAIT_S
    assert stop_wait_s(2.0) == 1.0


@slurm_only
def test_kill_wait_is_read_from_the_controller(slurm, monkeypatch) -> None:
    monkeypatch.setenv("SLURM_CONF", slurm.env()["SLURM_CONF"])
    assert kill_wait_s() == slurm.kill_wait_s


@slurm_only
def test_an_unreachable_controller_names_scontrol_ping(slurm, tmp_path, monkeypatch, capsys):
    # this cluster's config with the controller's port closed: a site whose slurmctld is down
    conf = tmp_path / "slurm.conf"
    text = slurm.conf.read_text()
    conf.write_text(text.replace(f"SlurmctldPort={slurm.ctld_port}", "SlurmctldPort=1"))
    (tmp_path / "gres.conf").write_text((slurm.conf.parent / "gres.conf").read_text())
    (tmp_path / "cgroup.conf").write_text((slurm.conf.parent / "cgroup.conf").read_text())
    monkeypatch.setenv("SLURM_CONF", str(conf))
    monkeypatch.setenv("SLURM_JOB_ID", "1")
    out = tmp_path / "run"
    assert main(["slurm", "conf/smoke.yaml", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "controller" in err and "scontrol ping" in err
    assert not out.exists()


@slurm_only
def test_a_default_slice_runs_under_slurm(slurm, tmp_path) -> None:
    """The embedded default (the tiny VLA on the tabletop simulator), one task, one episode per
    cell: the run dir, its per-step effects, the report and MLflow as from a local run."""
    out = tmp_path / "runs" / "default"
    log = tmp_path / "job.out"
    job = slurm.sbatch(
        "--nodes=1",  # the grid test above runs on two nodes
        "--cpus-per-task=2",
        f"--output={log}",
        str(SBATCH),
        "conf/default.yaml",
        str(out),
        "env.tasks=[pick_color]",
        "episodes_per_task=1",
        "executor.workers=1",
        cwd=ROOT,
    )
    info = slurm.wait_job(job, {"COMPLETED", "FAILED"}, 400)
    assert info["JobState"] == "COMPLETED", log.read_text()[-3000:]
    episodes = pq.read_table(out / "episodes").to_pylist()
    assert sorted(r["cell_id"] for r in episodes) == ["E", "diagnose"]
    steps = pq.read_table(out / "steps", columns=["e_img", "e_prop"])
    assert steps.num_rows > 10  # the per-step causal effects
    assert (out / "report.md").is_file() and (out.parent / "mlflow.db").is_file()


@slurm_only
def test_off_the_allocations_first_node_names_srun(slurm, tmp_path, monkeypatch, capsys):
    """Inside salloc the shell stays on the login node: the head would start off the
    allocation. Refused, naming the srun line that puts it on the first node."""
    import re

    got = subprocess.run(
        ["salloc", "--nodes=1", "--cpus-per-task=2", "--no-shell"],
        env=slurm.env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    job = re.search(r"allocation (\d+)", got.stderr).group(1)
    try:
        node = slurm.job(job)["NodeList"]
        for key, value in {
            "SLURM_CONF": str(slurm.conf),
            "SLURM_JOB_ID": job,
            "SLURM_JOB_NODELIST": node,
            "SLURM_JOB_CPUS_PER_NODE": "2",
        }.items():
            monkeypatch.setenv(key, value)
        monkeypatch.delenv("SLURMD_NODENAME", raising=False)
        out = tmp_path / "run"
        assert main(["slurm", "conf/smoke.yaml", "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert f"srun --nodes=1 --ntasks=1 --nodelist={node} idr-eval slurm" in err
        assert not out.exists()
    finally:
        subprocess.run(["scancel", job], env=slurm.env(), check=False)
