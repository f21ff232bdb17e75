"""A grid inside a Slurm allocation: Ray across its nodes, the driver on the first, and a clean
stop before Slurm's kill that the job's next start resumes.

    sbatch -N 2 docker/slurm.sbatch conf/grids/alpha.yaml /shared/runs/alpha
    idr-eval slurm CONFIG --out RUN_DIR [key=value ...]      # what the script runs

This follows Ray's Slurm pattern: the head on the allocation's first node (where the batch
script runs), one ``ray start --block`` per other node through ``srun``, and the driver
(``idr-eval run ... executor.address=HEAD:PORT``) on the head. Each Ray node gets the CPUs and
GPUs Slurm gave it on that node, so the allocation's GPUs are what policy actors are placed on.
``ray symmetric-run`` is not used: it ends with ``ray stop`` (every Ray of the user on the node,
another job's included), passes no signal on to its command, and takes no node address.

Before any Ray starts (one message, non-zero exit): outside an allocation (names ``sbatch`` and
``salloc``), controller unreachable (names ``scontrol ping``), an allocation smaller than the
config's actors (both numbers), and a run dir that not every node sees (each node writes a
token beside it through ``srun``; the driver must see them all).

Signals (the batch script asks for ``--requeue --signal=B:USR1@120``):

- USR1, Slurm's warning before the wall-time limit: the driver stops cleanly (results flushed,
  MLflow runs KILLED) and the launcher requeues the job with ``scontrol requeue``; its next
  start resumes the run dir. USR1, not TERM: TERM is also what ``scancel`` sends, so it cannot
  mean "requeue me".
- TERM (``scancel``, ``scontrol requeue``, preemption): the driver stops cleanly. Slurm requeues
  the job itself when it was requeued or preempted; after ``scancel``, submitting the same
  command again resumes.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import re
import secrets
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

from pipeline.errors import ConfigError, RunError

log = logging.getLogger("idr_eval.slurm")
NODE_WAIT_S = 120.0  # for every Ray node of the allocation to register
STOP_WAIT_S = 60.0  # for the driver to flush and exit after a stop signal
STOP_MARGIN_S = 5.0  # of Slurm's KillWait kept for the launcher's own stop event and Ray's stop
EVENTS = "slurm.jsonl"  # in the run dir: one line per start and stop of the launcher


def _scontrol(*args: str, timeout_s: float = 20.0) -> str:
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
        out = _scontrol("ping")
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
        m = re.search(r"^KillWait\s*=\s*(\d+)", _scontrol("show", "config"), re.MULTILINE)
        if m:
            return float(m.group(1))
    return None


def stop_wait_s(kill_wait: float | None) -> float:
    """How long the driver gets for its clean stop: STOP_WAIT_S, cut to end before Slurm's KILL
    would end the launcher too (which would then leave no stop event and no Ray logs)."""
    if kill_wait is None:
        return STOP_WAIT_S
    return max(1.0, min(STOP_WAIT_S, kill_wait - STOP_MARGIN_S))


def hostnames(nodelist: str) -> list[str]:
    return _scontrol("show", "hostnames", nodelist).split()


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
    for m in re.finditer(r"Nodes=(\S+) .*?GRES=(\S+)", _scontrol("show", "job", "-d", job_id)):
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
    m = re.search(r"NodeAddr=(\S+)", _scontrol("show", "node", node))
    return socket.gethostbyname(m.group(1) if m else node)


def _srun(node: str | None, alloc: Allocation, cmd: list[str]) -> list[str]:
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
        _srun(None, alloc, ["sh", "-c", script, str(control)]),
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


@dataclass
class RayOnSlurm:
    """The Ray nodes this launcher started: the head (a child) and one ``srun`` per node."""

    address: str
    procs: list[subprocess.Popen]

    def stop(self) -> None:
        for p in reversed(self.procs):  # workers first, the head last
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    continue
        deadline = time.monotonic() + 10
        for p in self.procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)


def _ray_bin() -> str:
    return str(Path(sys.executable).with_name("ray"))


def start_ray(alloc: Allocation, control: Path, env: dict[str, str]) -> RayOnSlurm:
    head = alloc.nodes[0]
    ip = node_address(head)
    with socket.socket() as s:  # a free port on the head for the GCS
        s.bind((ip, 0))
        port = s.getsockname()[1]
    address = f"{ip}:{port}"
    tmp = Path(os.environ.get("TMPDIR", "/tmp"))
    common = ["--block", "--disable-usage-stats"]
    procs = []
    log_dir = control / "ray-logs"
    log_dir.mkdir(exist_ok=True)

    def launch(cmd: list[str], name: str) -> None:
        with open(log_dir / f"{name}.log", "w") as f:
            procs.append(
                subprocess.Popen(
                    cmd, stdout=f, stderr=subprocess.STDOUT, env=env, start_new_session=True
                )
            )

    launch(
        [
            _ray_bin(),
            "start",
            "--head",
            f"--node-ip-address={ip}",
            f"--port={port}",
            f"--num-cpus={alloc.cpus[0]}",
            f"--num-gpus={alloc.gpus[0]}",
            f"--temp-dir={tmp / f'ray-{alloc.job_id}-{head}'}",
            "--include-dashboard=false",
            *common,
        ],
        head,
    )
    ray = RayOnSlurm(address, procs)
    try:
        # the other nodes start at once: `ray start --address` waits for the head's GCS
        for node, cpus, gpus in zip(alloc.nodes[1:], alloc.cpus[1:], alloc.gpus[1:], strict=True):
            cmd = [
                _ray_bin(),
                "start",
                f"--address={address}",
                f"--num-cpus={cpus}",
                f"--num-gpus={gpus}",
                f"--temp-dir={tmp / f'ray-{alloc.job_id}-{node}'}",
                *common,
            ]
            # in a container, `ray start` runs in it on every node (docker/slurm.sbatch)
            wrap = shlex.split(os.environ.get("IDR_EVAL_EXEC", ""))
            launch(_srun(node, alloc, [*wrap, *cmd]), node)
        _wait_nodes(address, len(alloc.nodes), procs)
    except BaseException:
        ray.stop()
        raise
    return ray


def _wait_nodes(address: str, n: int, procs: list[subprocess.Popen]) -> None:
    from ray._raylet import GcsClient
    from ray.core.generated.gcs_pb2 import GcsNodeInfo

    deadline = time.monotonic() + NODE_WAIT_S
    alive = 0
    while time.monotonic() < deadline:
        dead = [p for p in procs if p.poll() is not None]
        if dead:
            raise RunError(
                f"a Ray node of the allocation exited (rc {dead[0].returncode}) before the run "
                "started; its log is under the run dir's .slurm-JOBID/ray-logs"
            )
        try:
            client = GcsClient(address=address)
            alive = len(
                client.get_all_node_info(
                    timeout=2, state_filter=GcsNodeInfo.GcsNodeState.ALIVE
                ).values()
            )
        except Exception:  # the GCS is still starting
            alive = 0
        if alive >= n:
            return
        time.sleep(0.5)
    raise RunError(f"{alive} of {n} Ray nodes registered at {address} in {NODE_WAIT_S:.0f} s")


class _Stop:
    signum: int | None = None
    requeue = False


class EventLog:
    """This start's lines of RUN_DIR/slurm.jsonl, written as they happen once the driver has
    made the run dir (nothing may be written there before): a start Slurm SIGKILLs after its
    KillWait still leaves what it did."""

    def __init__(self, run_dir: Path) -> None:
        self.run_dir = run_dir
        self.pending: list[dict] = []

    def emit(self, event: str, **fields: object) -> None:
        self.pending.append({"t": round(time.time(), 3), "event": event, **fields})
        self.flush()

    def flush(self) -> None:
        from pipeline.rundir import RUN_JSON

        if self.pending and (self.run_dir / RUN_JSON).is_file():
            with (self.run_dir / EVENTS).open("a") as f:
                f.writelines(json.dumps(e) + "\n" for e in self.pending)
            self.pending.clear()


def _keep_ray_logs(run_dir: Path, control: Path, restarts: int) -> None:
    from pipeline.rundir import LOGS_DIR, RUN_JSON

    logs = control / "ray-logs"
    if logs.is_dir() and (run_dir / RUN_JSON).is_file():
        dest = run_dir / LOGS_DIR / f"ray-{control.name.removeprefix('.')}-{restarts}"
        shutil.rmtree(dest, ignore_errors=True)
        shutil.copytree(logs, dest)


def run(config: str, out: str, overrides: list[str], driver_args: list[str]) -> int:
    """Pre-flight, Ray across the allocation, the driver; returns the driver's exit code."""

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        _Stop.signum = signum
        _Stop.requeue = _Stop.requeue or signum == signal.SIGUSR1

    # first of all: USR1's default action would end this process before the driver is told
    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGUSR1, signal.SIGTERM)}
    try:
        return _run(config, out, overrides, driver_args)
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def _run(config: str, out: str, overrides: list[str], driver_args: list[str]) -> int:
    from pipeline.planning.config import load_config

    if any(o.startswith("executor.address=") for o in overrides):
        raise ConfigError(
            "executor.address is set by `idr-eval slurm` (the head it starts); drop it"
        )
    cfg = load_config(config, overrides)  # a bad config fails here, before Slurm is asked
    if not os.environ.get("SLURM_JOB_ID"):
        read_allocation()  # the message that names sbatch and salloc
    ping_controller()
    alloc = read_allocation()
    here = os.environ.get("SLURMD_NODENAME")
    if here != alloc.nodes[0]:
        # inside salloc the shell is on the login node: the head must be on the allocation
        raise ConfigError(
            f"`idr-eval slurm` runs on the allocation's first node ({alloc.nodes[0]}), this is "
            f"{here or 'not a node of it'}: submit docker/slurm.sbatch with sbatch, or inside "
            f"salloc run `srun --nodes=1 --ntasks=1 --nodelist={alloc.nodes[0]} idr-eval slurm "
            "...`"
        )
    gpus = sum(n * d.get("GPU", 0.0) for _, n, d in cfg.executor.actor_groups())
    check_fits(alloc, cfg.executor.local_cpus(), gpus)
    run_dir = Path(out).resolve()
    control = run_dir.parent / f".slurm-{alloc.job_id}-{run_dir.name}"
    try:
        check_shared(alloc, control, run_dir)
        warn_sqlite_on_network_fs(cfg.tracking.uri, run_dir)
        return _launch(config, run_dir, overrides, driver_args, alloc, control)
    finally:
        shutil.rmtree(control, ignore_errors=True)


def _launch(
    config: str,
    run_dir: Path,
    overrides: list[str],
    driver_args: list[str],
    alloc: Allocation,
    control: Path,
) -> int:
    token = control / "ray_auth_token"
    token.write_text(secrets.token_hex(32))
    token.chmod(0o600)
    # one token for this job's Ray: its nodes, the driver and this launcher's node count
    os.environ.update(
        RAY_AUTH_MODE="token", RAY_AUTH_TOKEN_PATH=str(token), RAY_USAGE_STATS_ENABLED="0"
    )
    os.environ.pop("RAY_AUTH_TOKEN", None)
    os.environ.pop("RAY_ADDRESS", None)
    env = dict(os.environ)
    t0 = time.time()
    events = EventLog(run_dir)
    events.emit(
        "start",
        job=alloc.job_id,
        restarts=alloc.restarts,
        nodes=list(alloc.nodes),
        cpus=list(alloc.cpus),
        gpus=list(alloc.gpus),
    )
    ray = start_ray(alloc, control, env)
    log.info("Ray on %d node(s) at %s in %.1f s", len(alloc.nodes), ray.address, time.time() - t0)
    events.emit("ray_up", address=ray.address)
    rc = 128 + (_Stop.signum or 0)
    killed = False
    try:
        if _Stop.signum is None:  # not stopped while Ray was starting
            wait_s = stop_wait_s(kill_wait_s())
            rc, killed = _drive(
                config, run_dir, overrides, driver_args, ray.address, env, events, wait_s
            )
        requeued = _Stop.requeue and rc != 0
        events.emit(
            "stop",
            rc=rc,
            signal=signal.Signals(_Stop.signum).name if _Stop.signum else None,
            requeued=requeued,
            driver_killed=killed,
        )
    finally:
        ray.stop()
    _keep_ray_logs(run_dir, control, alloc.restarts)
    if requeued:
        # the wall-time warning: back to the queue; the job's next start resumes the run dir
        _scontrol("requeue", alloc.job_id)
    return rc


def _drive(
    config: str,
    run_dir: Path,
    overrides: list[str],
    driver_args: list[str],
    address: str,
    env: dict[str, str],
    events: EventLog,
    wait_s: float,
) -> tuple[int, bool]:
    """``idr-eval run`` against this job's Ray; a stop signal becomes its clean stop (TERM),
    and a driver not done after ``wait_s`` is killed. Returns its exit code and whether it was
    killed."""
    cmd = [
        str(Path(sys.executable).with_name("idr-eval")),
        "run",
        config,
        "--out",
        str(run_dir),
        *driver_args,
        *overrides,
        f"executor.address={address}",
    ]
    driver = subprocess.Popen(cmd, env={**env, "RAY_ADDRESS": address})
    stop_deadline: float | None = None
    killed = False
    while True:
        try:
            return driver.wait(timeout=0.5), killed
        except subprocess.TimeoutExpired:
            events.flush()  # once the driver has made the run dir
        if _Stop.signum is not None and stop_deadline is None:
            driver.send_signal(signal.SIGTERM)  # flush, MLflow KILLED, exit 143
            stop_deadline = time.monotonic() + wait_s
        if stop_deadline is not None and time.monotonic() > stop_deadline and not killed:
            log.warning("the driver did not stop within %.0f s of the signal: killing it", wait_s)
            driver.kill()
            killed = True
