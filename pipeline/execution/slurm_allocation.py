"""What Slurm gave this job, read with ``scontrol``, and the checks made on it before any Ray
starts (``pipeline.execution.slurm``): inside an allocation, the controller up, enough CPUs and
GPUs for the config's actors, a run dir every node sees; ``srun`` command lines for one node or
all of them."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import ConfigError

log = logging.getLogger("idr_eval.slurm")


def scontrol(*args: str, timeout_s: float = 20.0) -> str:
    try:
        out = subprocess.run(
            ["scontrol", *args], capture_output=True, text=True, timeout=timeout_s, check=True
        )
    except FileNotFoundError:
        raise ConfigError(
            "scontrol is not on PATH: `idr-eval slurm` runs inside a Slurm allocation (submit "
            "with `sbatch docker/slurm.sbatch ...` or start one with `salloc`)"
        ) from None
    except (subprocess.CalledProcessError, subprocess.TimeoutExpired) as e:
        detail = (getattr(e, "stderr", "") or "").strip() or str(e)
        raise ConfigError(f"`scontrol {' '.join(args)}` failed: {detail}") from None
    return out.stdout


def ping_controller() -> None:
    """Refuse when Slurm's controller does not answer (before anything starts)."""
    try:
        out = scontrol("ping")
    except ConfigError as e:
        raise ConfigError(
            f"Slurm's controller is unreachable ({e}); check the daemons with `scontrol ping`"
        ) from None
    if "UP" not in out:
        raise ConfigError(
            f"Slurm's controller is down (`scontrol ping`: {out.strip()}); start slurmctld or "
            "check SLURM_CONF"
        )


def expand_counts(text: str) -> list[int]:
    """Slurm's compressed per-node counts: ``"2(x3),1"`` -> ``[2, 2, 2, 1]``."""
    out: list[int] = []
    for part in filter(None, text.split(",")):
        m = re.fullmatch(r"(\d+)(?:\(x(\d+)\))?", part.strip())
        if not m:
            raise ConfigError(f"cannot read Slurm's per-node count {text!r}")
        out += [int(m.group(1))] * int(m.group(2) or 1)
    return out


def gres_gpus(spec: str) -> int:
    """GPUs in a GRES string of ``scontrol show job -d``: ``gpu:a100:2(IDX:0-1),shard:0`` -> 2."""
    total = 0
    for item in re.split(r",(?![^(]*\))", spec):
        fields = item.split("(")[0].split(":")
        if fields[0] == "gpu" and fields[-1].isdigit():
            total += int(fields[-1])
    return total


@dataclass(frozen=True)
class Allocation:
    """The nodes of this job (the first runs the batch script) and what each was given."""

    job_id: str
    nodes: tuple[str, ...]
    cpus: tuple[int, ...]
    gpus: tuple[int, ...]
    restarts: int  # SLURM_RESTART_COUNT: how often the job was requeued

    @property
    def total_cpus(self) -> int:
        return sum(self.cpus)

    @property
    def total_gpus(self) -> int:
        return sum(self.gpus)


def kill_wait_s() -> float | None:
    """Slurm's KillWait: the seconds between a job's TERM and its KILL (None where unreadable)."""
    with contextlib.suppress(ConfigError):
        m = re.search(r"^KillWait\s*=\s*(\d+)", scontrol("show", "config"), re.MULTILINE)
        if m:
            return float(m.group(1))
    return None


def hostnames(nodelist: str) -> list[str]:
    return scontrol("show", "hostnames", nodelist).split()


def read_allocation(env: dict[str, str] | None = None) -> Allocation:
    env = dict(os.environ if env is None else env)
    job_id = env.get("SLURM_JOB_ID")
    if not job_id:
        raise ConfigError(
            "not inside a Slurm allocation (SLURM_JOB_ID is not set): submit with `sbatch "
            "docker/slurm.sbatch CONFIG RUN_DIR`, or run `idr-eval slurm` inside `salloc`"
        )
    nodes = hostnames(env["SLURM_JOB_NODELIST"])
    cpus = expand_counts(env.get("SLURM_JOB_CPUS_PER_NODE", ""))
    if len(cpus) != len(nodes):
        raise ConfigError(
            f"SLURM_JOB_CPUS_PER_NODE={env.get('SLURM_JOB_CPUS_PER_NODE')!r} does not give one "
            f"count per node of {nodes}"
        )
    gpus = dict.fromkeys(nodes, 0)
    # per node group: "Nodes=n[1-2] CPU_IDs=0-1 Mem=0 GRES=gpu:1(IDX:0)"
    for m in re.finditer(r"Nodes=(\S+) .*?GRES=(\S+)", scontrol("show", "job", "-d", job_id)):
        for node in hostnames(m.group(1)):
            if node in gpus:
                gpus[node] = gres_gpus(m.group(2))
    return Allocation(
        job_id,
        tuple(nodes),
        tuple(cpus),
        tuple(gpus[n] for n in nodes),
        int(env.get("SLURM_RESTART_COUNT", "0") or 0),
    )


def check_fits(alloc: Allocation, demand_cpus: float, demand_gpus: float) -> None:
    """Refuse an allocation smaller than what the run's actors ask for, with both numbers."""
    short = []
    if demand_cpus > alloc.total_cpus + 1e-9:
        short.append(f"{demand_cpus:g} CPUs but the allocation has {alloc.total_cpus}")
    if demand_gpus > alloc.total_gpus + 1e-9:
        short.append(f"{demand_gpus:g} GPUs but the allocation has {alloc.total_gpus}")
    if short:
        per_node = ", ".join(
            f"{n}: {c} CPU, {g} GPU"
            for n, c, g in zip(alloc.nodes, alloc.cpus, alloc.gpus, strict=True)
        )
        raise ConfigError(
            f"the config's actors ask for {' and '.join(short)} ({per_node}); ask sbatch for "
            "more (-N, --cpus-per-task, --gres=gpu:N) or lower executor.workers"
        )


def node_address(node: str) -> str:
    """The node's IP (its NodeAddr in Slurm, resolved): where its Ray node listens."""
    m = re.search(r"NodeAddr=(\S+)", scontrol("show", "node", node))
    return socket.gethostbyname(m.group(1) if m else node)


def srun_command(node: str | None, alloc: Allocation, cmd: list[str]) -> list[str]:
    """``cmd`` on ``node``, or once on every node of the allocation."""
    n = len(alloc.nodes)
    where = (
        ["--nodes=1", "--ntasks=1", f"--nodelist={node}"]
        if node
        else [f"--nodes={n}", f"--ntasks={n}", "--ntasks-per-node=1"]
    )
    # --overlap: a Ray node and a check may share a node's CPUs with the batch script
    return ["srun", "--overlap", "--kill-on-bad-exit=0", *where, *cmd]


def check_shared(alloc: Allocation, control: Path, run_dir: Path) -> None:
    """Every node writes a token into ``control`` (beside the run dir); refuse the run when the
    driver does not see one (a node-local path, another mount)."""
    control.mkdir(parents=True, exist_ok=True)
    script = 'echo "$SLURMD_NODENAME" > "$0/node-$SLURMD_NODENAME"'
    subprocess.run(
        srun_command(None, alloc, ["sh", "-c", script, str(control)]),
        capture_output=True,
        timeout=120,
    )
    missing = [n for n in alloc.nodes if not (control / f"node-{n}").is_file()]
    if missing:
        raise ConfigError(
            f"--out {run_dir}: node(s) {missing} of the allocation do not see {run_dir.parent} "
            f"(their token is missing from {control}); put the run dir on a filesystem every "
            "node mounts at the same path"
        )


def warn_sqlite_on_network_fs(tracking_uri: str | None, run_dir: Path) -> None:
    """A SQLite MLflow store on a network filesystem: MLflow's docs advise a tracking server."""
    if tracking_uri and not tracking_uri.startswith("sqlite:"):
        return
    db = Path(tracking_uri.removeprefix("sqlite:///")) if tracking_uri else run_dir
    fstype = _fstype(db if db.exists() else db.parent)
    if fstype in {"nfs", "nfs4", "lustre", "gpfs", "beegfs", "cifs", "smb3", "ceph", "fuse.sshfs"}:
        log.warning(
            "MLflow's SQLite store lies on %s (%s): SQLite's locking is unreliable on network "
            "filesystems; use a tracking server (tracking.uri=http://HOST:5000, see "
            "docs/mlflow.md)",
            fstype,
            db,
        )


def _fstype(path: Path) -> str:
    best, kind = "", ""
    try:
        mounts = Path("/proc/self/mounts").read_text().splitlines()
    except OSError:
        return ""
    target = str(path.resolve())
    for line in mounts:
        parts = line.split()
        if len(parts) > 2 and target.startswith(parts[1]) and len(parts[1]) > len(best):
            best, kind = parts[1], parts[2]
    return kind
