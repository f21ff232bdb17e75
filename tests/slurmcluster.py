"""A real Slurm on this machine, for the Slurm tests and benchmarks/bench_slurm.py.

Debian's slurm-wlm and munge, started as root: munged on its own socket, slurmctld on a bridge
this module creates, and one slurmd per node, each in a network namespace of its own with its
own address (``10.77.X.1`` the controller, ``.11``, ``.12``, ... the nodes), so every node is
what it is on a cluster: a host with an IP that Ray's nodes bind to. Only the bridge and the
namespaces made here carry traffic. A node can be given a private mount (``private={"n2":
PATH}``: a tmpfs over PATH seen only by that node's processes), the way a node-local disk looks.

GPUs: the nodes declare a count-only GRES (``gpu``, ``Flags=CountOnly``; Slurm 22.05 drops a
gpu entry without a device file, so ``File=/dev/null`` stands in): Slurm schedules and accounts
them, nothing touches CUDA. Everything is removed by :meth:`SlurmCluster.stop`.
"""

from __future__ import annotations

import contextlib
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

DAEMONS = ("munged", "slurmctld", "slurmd", "sbatch", "scontrol", "ip", "unshare")


def unavailable() -> str | None:
    """Why a real Slurm cannot be started here, or None."""
    if os.geteuid() != 0:
        return "the Slurm tests start slurmctld, slurmd and network namespaces: they need root"
    missing = [d for d in DAEMONS if shutil.which(d) is None]
    if missing:
        return f"{missing} not installed (Debian: apt-get install slurm-wlm munge iproute2)"
    probe = f"idrprobe{os.getpid()}"
    made = subprocess.run(["ip", "netns", "add", probe], capture_output=True)
    if made.returncode:
        return f"network namespaces are not permitted here: {made.stderr.decode().strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def sweep_stale() -> None:
    """Remove the namespaces, bridges and daemons of test processes that were killed before
    their teardown ran (their pid is in every name)."""
    for line in _sh("ip", "netns", "list", check=False).stdout.splitlines():
        m = re.match(r"idrs(\d+)n\d+", line)
        if m and not _alive(int(m.group(1))):
            ns = line.split()[0]
            for pid in _sh("ip", "netns", "pids", ns, check=False).stdout.split():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(int(pid), signal.SIGKILL)
            _sh("ip", "netns", "del", ns, check=False)
    for m in re.finditer(r"\d+: (idrbr(\d+))[:@]", _sh("ip", "link", check=False).stdout):
        if not _alive(int(m.group(2))):
            _sh("ip", "link", "del", m.group(1), check=False)
    for proc in Path("/proc").glob("[0-9]*/cmdline"):
        with contextlib.suppress(OSError):
            m = re.search(rb"/idr-slurm-(\d+)-", proc.read_bytes())
            if m and not _alive(int(m.group(1))):
                with contextlib.suppress(ProcessLookupError):
                    os.kill(int(proc.parent.name), signal.SIGKILL)


def _sh(*cmd: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, check=check)


def _free_port(host: str) -> int:
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


@dataclass
class SlurmCluster:
    """``with SlurmCluster(nodes=2) as sc:`` a controller and ``nodes`` slurmd, each node
    ``cpus`` CPUs and ``gpus`` count-only GPUs."""

    nodes: int = 2
    cpus: int = 2
    gpus: int = 1
    private: dict[str, Path] = field(default_factory=dict)
    root: Path = field(
        default_factory=lambda: Path(tempfile.mkdtemp(prefix=f"idr-slurm-{os.getpid()}-"))
    )
    kill_wait_s: int = 5

    def __post_init__(self) -> None:
        pid = os.getpid()  # in every name: sweep_stale() removes what a killed test left
        self.subnet = f"10.77.{random.randint(10, 250)}"
        self.bridge = f"idrbr{pid}"
        self.names = [f"n{i + 1}" for i in range(self.nodes)]
        self.netns = {n: f"idrs{pid}{n}" for n in self.names}
        self.conf = self.root / "etc" / "slurm.conf"
        self._made: list[tuple[str, ...]] = []  # undo commands, in reverse order

    # --- addresses and environment ----------------------------------------------------------
    @property
    def controller_ip(self) -> str:
        return f"{self.subnet}.1"

    def node_ip(self, node: str) -> str:
        return f"{self.subnet}.{10 + self.names.index(node) + 1}"

    def env(self) -> dict[str, str]:
        """The environment of a Slurm client (sbatch, scontrol) of this cluster."""
        return {**os.environ, "SLURM_CONF": str(self.conf)}

    # --- start / stop -----------------------------------------------------------------------
    def __enter__(self) -> SlurmCluster:
        try:
            self.start()
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def start(self) -> None:
        sweep_stale()
        self._network()
        self._munge()
        self._write_config()
        _sh("slurmctld", "-i", "-f", str(self.conf))
        self._made.append(("pidfile", str(self.root / "slurmctld.pid")))
        for node in self.names:
            self.start_node(node)
        self.wait_idle()

    def _network(self) -> None:
        _sh("ip", "link", "add", self.bridge, "type", "bridge")
        self._made.append(("ip", "link", "del", self.bridge))
        _sh("ip", "addr", "add", f"{self.controller_ip}/24", "dev", self.bridge)
        _sh("ip", "link", "set", self.bridge, "up")
        for node in self.names:
            ns, veth = self.netns[node], f"{self.netns[node]}v"[:15]
            _sh("ip", "netns", "add", ns)
            self._made.append(("ip", "netns", "del", ns))
            _sh("ip", "link", "add", veth, "type", "veth", "peer", "name", "eth0", "netns", ns)
            _sh("ip", "link", "set", veth, "master", self.bridge)
            _sh("ip", "link", "set", veth, "up")
            inside = ("ip", "netns", "exec", ns, "ip")
            _sh(*inside, "addr", "add", f"{self.node_ip(node)}/24", "dev", "eth0")
            _sh(*inside, "link", "set", "eth0", "up")
            _sh(*inside, "link", "set", "lo", "up")

    def _munge(self) -> None:
        key = self.root / "munge.key"
        key.write_bytes(os.urandom(1024))
        key.chmod(0o400)
        self.munge_socket = self.root / "munge.sock"
        _sh(
            "munged",
            "--force",
            f"--key-file={key}",
            f"--socket={self.munge_socket}",
            f"--pid-file={self.root / 'munged.pid'}",
            f"--log-file={self.root / 'munged.log'}",
            f"--seed-file={self.root / 'munged.seed'}",
        )
        self._made.append(("pidfile", str(self.root / "munged.pid")))

    def _write_config(self) -> None:
        r = self.root
        (r / "etc").mkdir(exist_ok=True)
        (r / "state").mkdir(exist_ok=True)
        self.ctld_port = _free_port(self.controller_ip)
        nodes = "\n".join(
            f"NodeName={n} NodeAddr={self.node_ip(n)} CPUs={self.cpus}"
            + (f" Gres=gpu:{self.gpus}" if self.gpus else "")
            + " State=UNKNOWN"
            for n in self.names
        )
        self.conf.write_text(
            f"""ClusterName=idrtest
SlurmctldHost={socket.gethostname()}({self.controller_ip})
SlurmctldPort={self.ctld_port}
SlurmdPort={_free_port(self.controller_ip)}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={self.munge_socket}
SlurmUser=root
SlurmdUser=root
MailProg=/bin/true
StateSaveLocation={r / "state"}
SlurmdSpoolDir={r / "spool-%n"}
SlurmctldPidFile={r / "slurmctld.pid"}
SlurmdPidFile={r / "slurmd-%n.pid"}
SlurmctldLogFile={r / "slurmctld.log"}
SlurmdLogFile={r / "slurmd-%n.log"}
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_CPU
SlurmdParameters=config_overrides
ReturnToService=2
MpiDefault=none
JobRequeue=1
GresTypes=gpu
KillWait={self.kill_wait_s}
MinJobAge=600
SlurmctldTimeout=10
SlurmdTimeout=10
InactiveLimit=0
SchedulerParameters=sched_interval=1
{nodes}
PartitionName=main Nodes={",".join(self.names)} Default=YES MaxTime=INFINITE State=UP
"""
        )
        if self.gpus:
            (r / "etc" / "gres.conf").write_text(
                f"NodeName={','.join(self.names)} Name=gpu Count={self.gpus} File=/dev/null "
                "Flags=CountOnly\n"
            )
        # the cgroup v1 hierarchy is mounted here, not v2 (slurmd's autodetection fails)
        (r / "etc" / "cgroup.conf").write_text("CgroupPlugin=cgroup/v1\nIgnoreSystemd=yes\n")

    def start_node(self, node: str) -> None:
        """Start (or restart) ``node``'s slurmd in its namespace (and private mount)."""
        cmd = ["slurmd", "-N", node, "-f", str(self.conf)]
        if node in self.private:
            path = self.private[node]
            path.mkdir(parents=True, exist_ok=True)
            script = f'mount -t tmpfs idr-private "{path}" && exec "$@"'
            cmd = ["unshare", "--mount", "--propagation", "private", "sh", "-c", script, "-", *cmd]
        _sh("ip", "netns", "exec", self.netns[node], *cmd)
        if node not in [m[-1] for m in self._made if m[0] == "node"]:
            self._made.append(("node", node))

    def kill_node(self, node: str) -> None:
        """SIGKILL everything in ``node``'s namespace (slurmd, its steps, a Ray node): a machine
        lost without a goodbye."""
        for pid in _sh("ip", "netns", "pids", self.netns[node], check=False).stdout.split():
            with contextlib.suppress(ProcessLookupError):
                os.kill(int(pid), signal.SIGKILL)

    def all_idle(self) -> bool:
        out = self.scontrol("show", "nodes", check=False).stdout
        states = [x.split("State=")[1].split()[0] for x in out.splitlines() if "State=" in x]
        return len(states) == self.nodes and all(s == "IDLE" for s in states)

    def wait_idle(self, timeout_s: float = 60) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            out = self.scontrol("show", "nodes", check=False).stdout
            states = [
                line.split("State=")[1].split()[0] for line in out.splitlines() if "State=" in line
            ]
            if len(states) == self.nodes and all(s.startswith("IDLE") for s in states):
                return
            if any("DOWN" in s or "DRAIN" in s for s in states):
                self.scontrol(
                    "update", f"nodename={','.join(self.names)}", "state=resume", check=False
                )
            time.sleep(0.5)
        raise TimeoutError(f"Slurm nodes not idle after {timeout_s:.0f} s: {states}")

    def stop(self) -> None:
        for node in self.names:
            self.kill_node(node)
        for undo in reversed(self._made):
            if undo[0] == "pidfile":
                with contextlib.suppress(OSError, ValueError):
                    os.kill(int(Path(undo[1]).read_text().strip()), signal.SIGTERM)
            elif undo[0] != "node":
                subprocess.run(undo, capture_output=True)
        self._made.clear()
        time.sleep(0.5)
        shutil.rmtree(self.root, ignore_errors=True)

    # --- clients ----------------------------------------------------------------------------
    def scontrol(self, *args: str, check: bool = True) -> subprocess.CompletedProcess:
        return subprocess.run(
            ["scontrol", *args], capture_output=True, text=True, env=self.env(), check=check
        )

    def sbatch(self, *args: str, cwd: Path | None = None) -> str:
        out = subprocess.run(
            ["sbatch", "--parsable", *args],
            capture_output=True,
            text=True,
            env=self.env(),
            cwd=cwd,
            check=True,
        )
        return out.stdout.strip().split(";")[0]

    def job(self, job_id: str) -> dict[str, str]:
        """``scontrol show job``'s KEY=VALUE fields ({} once the job is forgotten)."""
        out = self.scontrol("show", "job", job_id, check=False).stdout
        fields: dict[str, str] = {}
        for token in out.split():
            key, sep, value = token.partition("=")
            if sep and key not in fields:
                fields[key] = value
        return fields

    def wait_job(self, job_id: str, states: set[str], timeout_s: float) -> dict[str, str]:
        deadline = time.monotonic() + timeout_s
        info: dict[str, str] = {}
        while time.monotonic() < deadline:
            info = self.job(job_id)
            if info.get("JobState") in states:
                return info
            time.sleep(0.3)
        raise TimeoutError(f"job {job_id} not in {states} after {timeout_s:.0f} s: {info}")
