"""Env servers: the Env protocol over a child process, and its lifecycle (start, health check,
restart with the episode run again, kill on timeout, never left behind).

The server runs the fake envs in another Python process (this interpreter: the protocol and
the lifecycle do not depend on which; CALVIN's own tests run it from Python 3.11)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from workers.envs.checks import check_env
from workers.envs.fakes import FakeMarkerEnv
from workers.envs.server.client import (
    EnvServerClient,
    EnvServerDied,
    EnvServerStartError,
    EnvServerTimeout,
    ServerSpec,
    probe_server,
)

SERVER = ServerSpec(python=sys.executable, timeout_s=30)
FAULTY = "tests.doubles.envs:ServerFaultEnv"


def _gone(pid: int, within_s: float = 5.0) -> bool:
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return True
        try:  # a zombie of ours counts as gone once reaped
            if os.waitpid(pid, os.WNOHANG)[0] == pid:
                return True
        except ChildProcessError:
            pass
        time.sleep(0.05)
    return False


@pytest.fixture
def remote():
    env = EnvServerClient("workers.envs.fakes:FakeMarkerEnv", {}, SERVER)
    yield env
    env.close()


def test_a_remote_env_passes_the_env_contract(remote):
    check_env(remote, task_id="reach_chain", run_to_horizon=True)


def test_same_observations_and_status_as_in_process(remote):
    local = FakeMarkerEnv()
    rng = np.random.default_rng(0)
    for episode in range(3):
        a, b = remote.reset("reach_chain", episode, 7), local.reset("reach_chain", episode, 7)
        while True:
            assert np.array_equal(a.state, b.state) and a.state.dtype == b.state.dtype
            assert np.array_equal(a.images["agentview"], b.images["agentview"])
            assert a.status == b.status  # steps, success, subtasks, done, instruction, task, info
            if b.status.done:
                break
            action = rng.uniform(-1, 1, 2).astype(np.float32)
            a, b = remote.step(action), local.step(action)


def test_errors_of_the_env_keep_their_type_and_say_where(remote):
    remote.reset("reach", 0, 0)
    with pytest.raises(ValueError, match="raised in the env server during 'step'"):
        remote.step(np.zeros(5, dtype=np.float32))
    with pytest.raises(ValueError, match="unknown"):
        remote.reset("no_such_task", 0, 0)
    assert remote.alive  # the env's own errors leave the server serving


def test_images_are_rendered_lazily_per_camera_and_only_while_current(tmp_path):
    log = tmp_path / "renders.log"
    env = EnvServerClient(FAULTY, {"render_log": str(log)}, SERVER)
    try:
        obs = env.reset("reach", 0, 0)
        for _ in range(3):  # open-loop steps: nobody reads their images
            obs = env.step(np.zeros(2, dtype=np.float32))
        assert not log.exists()
        first = obs.images["agentview"]
        assert obs.images["agentview"] is first  # rendered once, then cached
        assert log.read_text().split() == ["agentview"]
        assert first.shape == (32, 32, 3) and first.dtype == np.uint8
    finally:
        env.close()


def test_a_stale_image_cannot_be_read_after_a_step(tmp_path):
    env = EnvServerClient(FAULTY, {"render_log": str(tmp_path / "r.log")}, SERVER)
    try:
        obs = env.reset("reach", 0, 0)
        env.step(np.zeros(2, dtype=np.float32))
        with pytest.raises(RuntimeError, match="stepped past"):
            obs.images["agentview"]
    finally:
        env.close()


def test_a_server_that_dies_mid_episode_is_an_error_of_the_server_with_its_output():
    env = EnvServerClient(FAULTY, {"exit_at_step": 3}, SERVER)
    pid = env.pid
    try:
        env.reset("reach", 0, 0)
        env.step(np.zeros(2, dtype=np.float32))
        env.step(np.zeros(2, dtype=np.float32))
        with pytest.raises(EnvServerDied, match=r"died during 'step' \(exit code 9\)"):
            env.step(np.zeros(2, dtype=np.float32))
        assert _gone(pid)
        env.reset("reach", 0, 0)  # health check: a new server, the same env
        assert env.alive and env.pid != pid and env.restarts == 1
    finally:
        env.close()


def test_a_server_that_hangs_is_killed_after_the_timeout():
    env = EnvServerClient(FAULTY, {"hang_at_step": 2}, ServerSpec(sys.executable, timeout_s=1.0))
    pid = env.pid
    try:
        env.reset("reach", 0, 0)
        env.step(np.zeros(2, dtype=np.float32))
        t0 = time.monotonic()
        with pytest.raises(EnvServerTimeout, match=r"did not answer 'step' within 1 s"):
            env.step(np.zeros(2, dtype=np.float32))
        assert time.monotonic() - t0 < 5
        assert _gone(pid)
    finally:
        env.close()


def test_close_is_idempotent_and_leaves_no_process(remote):
    pid = remote.pid
    remote.close()
    remote.close()
    assert _gone(pid)


_PARENT = textwrap.dedent(
    """
    import sys, threading, time
    from workers.envs.server.client import EnvServerClient, ServerSpec
    box = {}
    def start():
        box["env"] = EnvServerClient("workers.envs.fakes:FakeMarkerEnv", {}, ServerSpec(sys.executable))
    if sys.argv[1] == "thread":  # no PR_SET_PDEATHSIG from a thread: the watchdog must do it
        t = threading.Thread(target=start); t.start(); t.join()
    else:
        start()
    print(box["env"].pid, flush=True)
    time.sleep(600)
    """
)


@pytest.mark.parametrize("started_from", ["main", "thread"])
def test_the_server_never_outlives_its_actor(started_from):
    root = Path(__file__).resolve().parents[3]
    parent = subprocess.Popen(
        [sys.executable, "-c", _PARENT, started_from],
        stdout=subprocess.PIPE,
        text=True,
        cwd=root,
        env={**os.environ, "PYTHONPATH": str(root)},
    )
    try:
        server_pid = int(parent.stdout.readline())
        os.kill(server_pid, 0)  # it runs
        parent.send_signal(signal.SIGKILL)  # the actor dies without closing anything
        parent.wait()
        assert _gone(server_pid, within_s=5), f"env server {server_pid} outlived its parent"
    finally:
        parent.kill()


def test_an_interpreter_without_the_wire_packages_is_refused_clearly(tmp_path):
    bare = tmp_path / "bare-python"
    bare.write_text(f'#!/bin/sh\nexec {sys.executable} -S -I "$@"\n')  # no site-packages
    bare.chmod(0o755)
    with pytest.raises(EnvServerStartError, match="needs numpy and msgpack"):
        EnvServerClient("workers.envs.fakes:FakeMarkerEnv", {}, ServerSpec(str(bare), timeout_s=10))


def test_a_server_of_another_protocol_version_is_refused(tmp_path):
    other = tmp_path / "other-version-python"
    code = (
        "import sys, workers.envs.server.wire as w; w.PROTOCOL_VERSION = 99; "
        "from workers.envs.server.serve import main; sys.exit(main(sys.argv[1:]))"
    )
    # called as `python -m workers.envs.server.serve --fd ...`: drop the -m and the module name
    other.write_text(f"#!/bin/sh\nshift 2\nexec {sys.executable} -c '{code}' \"$@\"\n")
    other.chmod(0o755)
    with pytest.raises(EnvServerStartError, match="speaks protocol version 99"):
        EnvServerClient(
            "workers.envs.fakes:FakeMarkerEnv", {}, ServerSpec(str(other), timeout_s=10)
        )


def test_a_missing_interpreter_is_refused():
    with pytest.raises(EnvServerStartError, match="cannot start the env server"):
        EnvServerClient("workers.envs.fakes:FakeMarkerEnv", {}, ServerSpec("/nonexistent/python"))


def test_probe_runs_the_envs_runtime_check_in_the_server(tmp_path):
    hello = probe_server(SERVER, FAULTY, {"missing_checkout": str(tmp_path)})
    assert hello["python"] == sys.version.split()[0]
    with pytest.raises(ValueError, match=r"env.params.missing_checkout=.*no such checkout"):
        probe_server(SERVER, FAULTY, {"missing_checkout": str(tmp_path / "nope")})
