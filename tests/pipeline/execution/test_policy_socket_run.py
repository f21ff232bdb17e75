"""A shared-policy run (batching fixed) with a local peer hammering its policy socket: peers
without the token, with a wrong one, with the token and oversized or malformed frames, and
more connections than the cap. The run's tables equal those of the same run undisturbed; the
refusals are counted in the run's log; the socket listens on loopback only (a local Ray); the
run's token is in the run dir, mode 0600, and nowhere in its log. Loopback only."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import stat
import struct
import threading
import time
from pathlib import Path

import pandas as pd
import psutil
import pytest

from pipeline.execution.runner import execute, plan_run, run_params
from pipeline.execution.worker_setup import policy_socket, with_policy_token
from pipeline.planning.config import load_config
from pipeline.rundir import LOGS_DIR, POLICY_TOKEN_FILE
from tests.pipeline.execution.test_runner import _episodes, _steps
from workers.io_spec import EnvIO
from workers.policy.socket_settings import DEFAULT_MAX_FRAME, SocketToken, frame_bound

CONF = Path(__file__).resolve().parents[3] / "conf"
SHARED = [
    "tracking.enabled=false",
    "executor.kind=ray",
    "executor.policy=shared",
    "executor.cpus_per_worker=0.5",
    "executor.policy_cpus=1",
    "executor.envs_per_worker=3",
    "executor.batch_wait_ms=5",
    "executor.batching=fixed",
]


def _policy_ports() -> list[tuple[str, int]]:
    """Listening TCP addresses of this machine's policy actors (Ray titles their processes
    ``ray::BatchingPolicyActor``)."""
    found = []
    for proc in psutil.process_iter(["cmdline"]):
        if "BatchingPolicyActor" not in " ".join(proc.info["cmdline"] or ()):
            continue
        try:
            conns = proc.net_connections(kind="tcp")
        except psutil.Error:
            continue
        found += [c.laddr for c in conns if c.status == psutil.CONN_LISTEN]
    return [(a.ip, a.port) for a in found]


class Hammer(threading.Thread):
    """A local peer: while the run goes, every policy socket on loopback gets connections
    without the token, with a wrong one, with the run's token (read from the run dir, as
    another process of this user could) and then an oversized or undecodable frame, and bursts
    of connections that hold the right token past the cap."""

    def __init__(self, run_dir: Path) -> None:
        super().__init__(daemon=True)
        self.run_dir = run_dir
        self.stop = threading.Event()
        self.sent = 0
        self.addresses: set[tuple[str, int]] = set()

    def _hit(self, address: tuple[str, int], data: bytes) -> None:
        try:
            with socket.create_connection(address, timeout=1.0) as s:
                s.sendall(data)
                s.settimeout(0.2)
                with contextlib.suppress(OSError):
                    s.recv(64)
            self.sent += 1
        except OSError:
            pass

    def run(self) -> None:
        token_file = self.run_dir / POLICY_TOKEN_FILE
        while not self.stop.is_set():
            ports = [a for a in _policy_ports() if a[0] == "127.0.0.1"]
            if not ports or not token_file.exists():
                time.sleep(0.05)
                continue
            token = SocketToken.from_hex(token_file.read_text())
            for address in ports:
                self.addresses.add(address)
                self._hit(address, b"GET / HTTP/1.1\r\nHost: x\r\n\r\n" + b"x" * 40)
                self._hit(address, SocketToken.new().auth_frame() + struct.pack("!I", 8) + b"x" * 8)
                self._hit(address, token.auth_frame() + struct.pack("!I", 1 << 30))
                self._hit(address, token.auth_frame() + struct.pack("!I", 4) + b"\xc1\xc1\xc1\xc1")
                burst = []
                for _ in range(40):  # above the cap (2 x 6 episodes + 8 = 20)
                    try:
                        c = socket.create_connection(address, timeout=1.0)
                        c.sendall(token.auth_frame())
                        burst.append(c)
                    except OSError:
                        break
                time.sleep(0.05)
                for c in burst:
                    c.close()
                self.sent += len(burst)


@pytest.mark.slow
def test_a_peer_hammering_the_policy_socket_changes_no_table(tmp_path, ray_local, caplog) -> None:
    cfg = load_config(CONF / "smoke.yaml", SHARED)
    quiet = execute(plan_run(cfg, tmp_path / "quiet"))
    assert quiet.stored == 12 and quiet.errors == 0

    hammer = Hammer(tmp_path / "hammered")
    hammer.start()
    caplog.clear()  # the quiet run's own socket line is not the hammered run's
    with caplog.at_level(logging.INFO, logger="idr_eval.executors.ray"):
        hammered = execute(plan_run(cfg, tmp_path / "hammered"))
    hammer.stop.set()
    hammer.join(timeout=30)
    assert hammered.stored == 12 and hammered.errors == 0
    assert hammer.addresses and hammer.sent > 40  # it did hammer, on loopback
    pd.testing.assert_frame_equal(_episodes(tmp_path / "quiet"), _episodes(tmp_path / "hammered"))
    pd.testing.assert_frame_equal(_steps(tmp_path / "quiet"), _steps(tmp_path / "hammered"))

    # the refusals, counted in the run's log by kind
    lines = [r.getMessage() for r in caplog.records if "socket:" in r.getMessage()]
    assert lines and all("refused or closed" in ln for ln in lines), lines
    refused = " ".join(lines)
    for kind in ("bad_token", "oversized", "malformed", "over_cap"):
        assert kind in refused, refused
    # the socket listens on loopback only; the token is the run's, 0600, in no log
    token_file = tmp_path / "hammered" / POLICY_TOKEN_FILE
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    secret = token_file.read_text().strip()
    for log_file in (tmp_path / "hammered" / LOGS_DIR).glob("*"):
        assert secret not in log_file.read_text(errors="replace"), log_file
    assert all(r.getMessage().find(secret) < 0 for r in caplog.records)


def test_a_local_ray_binds_loopback_a_cluster_the_node_and_the_bounds_follow_the_config(
    tmp_path, monkeypatch
) -> None:
    cfg = load_config(CONF / "smoke.yaml", SHARED)
    local = policy_socket(cfg, tmp_path)
    assert local is not None and local.host == "127.0.0.1" and local.bind_host() == "127.0.0.1"
    assert local.limits.max_connections == 2 * 6 + 8  # 2 actors x 3 envs in flight
    assert local.limits.idle_timeout_s == 900.0 and local.limits.max_frame == DEFAULT_MAX_FRAME
    assert (
        local.token is None and not (tmp_path / POLICY_TOKEN_FILE).exists()
    )  # planning writes nothing
    plan = plan_run(cfg, tmp_path / "run")
    started = with_policy_token(plan).worker_spec.policy_socket
    assert started.token == SocketToken.from_hex((tmp_path / "run" / POLICY_TOKEN_FILE).read_text())
    assert with_policy_token(plan).worker_spec.policy_socket.token == started.token  # kept
    secret = (tmp_path / "run" / POLICY_TOKEN_FILE).read_text().strip()
    assert secret not in json.dumps(run_params(plan), default=str)  # no MLflow param holds it
    assert secret not in repr(with_policy_token(plan))
    cluster = ["executor.address=10.0.0.1:6379", "executor.policy_connections=5"]
    on_cluster = load_config(
        CONF / "smoke.yaml", [*SHARED, *cluster, "executor.episode_timeout_s=120"]
    )
    remote = policy_socket(on_cluster, tmp_path)
    assert remote is not None and remote.host is None  # the node's address, with the token
    assert remote.limits.max_connections == 5 and remote.limits.idle_timeout_s == 120
    # an env that describes itself bounds the frames by its images and dims
    io = EnvIO(cameras=("agentview", "wrist"), image_size=128, state_dim=8, action_dim=7)
    monkeypatch.setattr("pipeline.planning.checkpoint_fit.describe_env", lambda suite, params: io)
    assert policy_socket(cfg, tmp_path).limits.max_frame == frame_bound(io)
    ray_calls = load_config(CONF / "smoke.yaml", [*SHARED, "executor.policy_transport=ray"])
    assert policy_socket(ray_calls, tmp_path) is None
