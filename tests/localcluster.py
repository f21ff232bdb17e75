"""Real servers on one machine, for the cluster tests and benchmarks/bench_cluster.py.

- :class:`RayCluster`: a Ray head and more nodes started with ``ray start`` (each its own
  ports, temp dir and process session), so several nodes on one box are a real cluster.
- :class:`Postgres`: a throwaway PostgreSQL cluster (``initdb`` as an unprivileged user when
  run as root), on a free port of 127.0.0.1.
- :class:`MlflowServer`: ``mlflow server`` backed by that PostgreSQL.

Every process is started in a new process session and stopped by killing exactly the
processes of that session (never ``ray stop``, which would kill every Ray on the machine,
other tests' and other users' included). Everything listens on 127.0.0.1 only.
"""

from __future__ import annotations

import contextlib
import glob
import os
import pwd
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

BIN = Path(sys.executable).parent  # the venv's bin: ray, mlflow, idr-eval
LOCALHOST = "127.0.0.1"
NODE_IP = "127.0.0.2"  # a loopback address Ray keeps as it is (127.0.0.1 it swaps for the host IP)
# Node loss is detected by the GCS health check: period x threshold (defaults 3 s x 5). The
# tests shorten it so that a lost node is noticed in ~2 s; a real cluster keeps the defaults.
FAST_HEALTH_CHECK = {
    "RAY_health_check_initial_delay_ms": "1000",
    "RAY_health_check_period_ms": "500",
    "RAY_health_check_timeout_ms": "500",
    "RAY_health_check_failure_threshold": "3",
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind((LOCALHOST, 0))
        return s.getsockname()[1]


def session_pids(sid: int) -> list[int]:
    """Processes whose session id is ``sid`` (what a process started with setsid spawned)."""
    out = []
    for stat in glob.glob("/proc/[0-9]*/stat"):
        try:
            text = Path(stat).read_text()
        except OSError:
            continue
        fields = text.rsplit(")", 1)[1].split()
        # fields after "(comm)": state ppid pgrp session ...; a zombie is dead already
        if int(fields[3]) == sid and fields[0] != "Z":
            out.append(int(stat.split("/")[2]))
    return out


def kill_session(sid: int, sig: int = signal.SIGKILL, wait_s: float = 10.0) -> None:
    """Send ``sig`` to every process of session ``sid`` and wait until they are gone."""
    deadline = time.monotonic() + wait_s
    while True:
        pids = session_pids(sid)
        if not pids:
            return
        for pid in pids:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)
        if time.monotonic() > deadline:
            return
        time.sleep(0.1)


def _wait_port(port: int, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        with socket.socket() as s:
            s.settimeout(0.5)
            if s.connect_ex((LOCALHOST, port)) == 0:
                return
        time.sleep(0.2)
    raise TimeoutError(f"{what} did not listen on {LOCALHOST}:{port} within {timeout_s:.0f} s")


@dataclass
class RayNode:
    name: str
    temp_dir: Path
    sid: int  # the process session of everything this node runs
    log: Path

    @property
    def node_id(self) -> str:
        """The Ray node id (hex), read from the port files Ray names after it."""
        found = glob.glob(str(self.temp_dir / "session_latest" / "runtime_env_agent_port_*"))
        if not found:
            raise RuntimeError(f"{self.name}: no node id under {self.temp_dir}")
        return Path(found[0]).name.rsplit("_", 1)[1]

    def kill(self) -> None:
        """SIGKILL every process of this node (as a lost machine would): no goodbye to the GCS."""
        kill_session(self.sid)


@dataclass
class RayCluster:
    """``ray start`` nodes on 127.0.0.1; use as a context manager (or call :meth:`stop`)."""

    root: Path = field(default_factory=lambda: Path(tempfile.mkdtemp(prefix="idr-ray-")))
    env: dict[str, str] = field(default_factory=dict)
    nodes: list[RayNode] = field(default_factory=list)
    gcs_port: int = 0
    dashboard_port: int | None = None

    @property
    def address(self) -> str:
        return f"{NODE_IP}:{self.gcs_port}"

    @property
    def dashboard_url(self) -> str:
        return f"http://{LOCALHOST}:{self.dashboard_port}"

    def __post_init__(self) -> None:
        # Ray 2.5x+ turns token authentication on for a new cluster; every process that
        # talks to this one (nodes, drivers, `ray job submit`) gets its own token from env().
        token = self.root / "auth_token"
        token.write_text(secrets.token_hex(32))
        token.chmod(0o600)
        self.env = {"RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN_PATH": str(token), **self.env}

    def client_env(self) -> dict[str, str]:
        """The environment of a driver of this cluster (``idr-eval run``, ``ray job submit``)."""
        env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_AUTH_TOKEN")}
        env["PATH"] = f"{BIN}{os.pathsep}{env.get('PATH', '')}"
        return {**env, "RAY_USAGE_STATS_ENABLED": "0", **self.env}

    _env = client_env

    def add_node(
        self,
        num_cpus: float,
        num_gpus: float = 0,
        resources: dict[str, float] | None = None,
        dashboard: bool = False,
        timeout_s: float = 120,
    ) -> RayNode:
        """Start a node (the first one is the head) and wait until it is registered."""
        import json

        head = not self.nodes
        name = "head" if head else f"node{len(self.nodes)}"
        temp_dir = self.root / name
        temp_dir.mkdir(parents=True, exist_ok=True)
        cmd = [
            str(BIN / "ray"),
            "start",
            f"--num-cpus={num_cpus:g}",
            f"--num-gpus={num_gpus:g}",
            f"--temp-dir={temp_dir}",
            f"--node-ip-address={NODE_IP}",
            f"--dashboard-agent-listen-port={free_port()}",
            f"--dashboard-agent-grpc-port={free_port()}",
            f"--runtime-env-agent-port={free_port()}",
            f"--metrics-export-port={free_port()}",
            "--disable-usage-stats",
        ]
        if resources:
            cmd.append(f"--resources={json.dumps(resources)}")
        if head:
            self.gcs_port = free_port()
            cmd += [
                "--head",
                f"--port={self.gcs_port}",
                f"--ray-client-server-port={free_port()}",
                f"--include-dashboard={'true' if dashboard else 'false'}",
            ]
            if dashboard:
                self.dashboard_port = free_port()
                cmd += [f"--dashboard-host={LOCALHOST}", f"--dashboard-port={self.dashboard_port}"]
        else:
            cmd += [f"--address={self.address}", "--include-log-monitor=false"]
        log = self.root / f"{name}.log"
        with open(log, "w") as f:
            # a new session: what this node spawns (raylet, workers) is found and killed by it
            proc = subprocess.Popen(
                cmd, stdout=f, stderr=subprocess.STDOUT, env=self._env(), start_new_session=True
            )
            node = RayNode(name, temp_dir, proc.pid, log)
            self.nodes.append(node)
            try:
                rc = proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                rc = None
        if rc != 0:
            raise RuntimeError(f"ray start ({name}) failed (rc={rc}):\n{log.read_text()[-3000:]}")
        if head and dashboard:
            _wait_port(self.dashboard_port, timeout_s, "the Ray dashboard")
        return node

    def stop(self) -> None:
        """Kill every process of every node (their sessions only), remove the temp dirs."""
        for node in reversed(self.nodes):
            node.kill()
        self.nodes.clear()
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> RayCluster:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def _unprivileged() -> tuple[int, int] | None:
    """PostgreSQL refuses to run as root: (uid, gid) of ``nobody`` then, else None."""
    if os.geteuid() != 0:
        return None
    pw = pwd.getpwnam("nobody")
    return pw.pw_uid, pw.pw_gid


def postgres_bin() -> Path | None:
    """Debian's PostgreSQL binaries (/usr/lib/postgresql/<ver>/bin), newest first; or PATH."""
    for d in sorted(glob.glob("/usr/lib/postgresql/*/bin"), reverse=True):
        if (Path(d) / "initdb").is_file():
            return Path(d)
    found = shutil.which("initdb")
    return Path(found).parent if found else None


class Postgres:
    """A throwaway PostgreSQL cluster on 127.0.0.1:<free port> (trust auth, local only)."""

    def __init__(self, user: str = "idr") -> None:
        bindir = postgres_bin()
        if bindir is None:
            raise RuntimeError("PostgreSQL is not installed (initdb not found)")
        self.bin, self.user, self.port = bindir, user, free_port()
        self.root = Path(tempfile.mkdtemp(prefix="idr-pg-"))
        self.data, self.sock = self.root / "data", self.root / "sock"
        self.sock.mkdir()
        self._ids = _unprivileged()
        if self._ids:
            for p in (self.root, self.sock):
                os.chown(p, *self._ids)
            self.root.chmod(0o755)
        self.sid: int | None = None

    @property
    def url(self) -> str:
        return f"postgresql://{self.user}@{LOCALHOST}:{self.port}/mlflow"

    def _run(self, *cmd: str) -> None:
        kw = {"user": self._ids[0], "group": self._ids[1]} if self._ids else {}
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=120, **kw)
        if out.returncode != 0:
            raise RuntimeError(f"{cmd[0]} failed: {out.stdout}{out.stderr}")

    def start(self) -> Postgres:
        b = self.bin
        self._run(
            str(b / "initdb"), "-D", str(self.data), "-U", self.user, "--auth=trust", "-E", "UTF8"
        )
        log = self.root / "postgres.log"
        kw = {"user": self._ids[0], "group": self._ids[1]} if self._ids else {}
        proc = subprocess.Popen(
            [
                str(b / "postgres"),
                "-D",
                str(self.data),
                "-p",
                str(self.port),
                "-k",
                str(self.sock),
                "-c",
                f"listen_addresses={LOCALHOST}",
                "-c",
                "fsync=off",
            ],
            stdout=subprocess.DEVNULL,
            stderr=open(log, "w"),  # noqa: SIM115 (the server keeps it)
            start_new_session=True,
            **kw,
        )
        self.sid = proc.pid
        deadline = time.monotonic() + 60
        while True:
            ok = subprocess.run(
                [str(b / "pg_isready"), "-h", LOCALHOST, "-p", str(self.port)],
                capture_output=True,
            )
            if ok.returncode == 0:
                break
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"postgres did not start:\n{log.read_text()[-2000:]}")
            time.sleep(0.2)
        self._run(
            str(b / "createdb"), "-h", LOCALHOST, "-p", str(self.port), "-U", self.user, "mlflow"
        )
        return self

    def stop(self) -> None:
        if self.sid is not None:
            kill_session(self.sid, signal.SIGINT, wait_s=10)  # fast shutdown
            kill_session(self.sid)
            self.sid = None
        shutil.rmtree(self.root, ignore_errors=True)

    def __enter__(self) -> Postgres:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()


class MlflowServer:
    """``mlflow server`` on 127.0.0.1:<port> with ``backend`` as its store; restartable."""

    def __init__(self, backend: str, artifacts: Path, port: int | None = None) -> None:
        self.backend, self.artifacts = backend, artifacts
        self.port = port or free_port()
        self.sid: int | None = None
        self.log = artifacts.parent / f"mlflow-server-{self.port}.log"

    @property
    def uri(self) -> str:
        return f"http://{LOCALHOST}:{self.port}"

    def start(self, timeout_s: float = 180) -> MlflowServer:
        self.artifacts.mkdir(parents=True, exist_ok=True)
        cmd = [
            str(BIN / "mlflow"),
            "server",
            "--backend-store-uri",
            self.backend,
            "--artifacts-destination",
            str(self.artifacts),
            "--host",
            LOCALHOST,
            "--port",
            str(self.port),
            "--workers",
            "1",
        ]
        # no job runner (7 huey consumers): idr-eval logs runs, params, metrics and artifacts
        env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
        with open(self.log, "a") as f:
            proc = subprocess.Popen(
                cmd,
                stdout=f,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                cwd=self.artifacts.parent,
                env=env,
            )
        self.sid = proc.pid
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                with urllib.request.urlopen(self.uri + "/health", timeout=2) as r:
                    if r.status == 200:
                        return self
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                raise RuntimeError(f"mlflow server did not start:\n{self.log.read_text()[-3000:]}")
            time.sleep(0.3)

    def stop(self) -> None:
        if self.sid is not None:
            kill_session(self.sid)
            self.sid = None

    def __enter__(self) -> MlflowServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
