"""The remote backbone against a fake policy server speaking openpi's websocket protocol
(another process): the codec, IDR's three passes with exact effects, noise, faults."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from idr_core.refiner import RefinerConfig

from workers.backbones.websocket import codec
from workers.backbones.websocket.client import RemoteBackboneError, WebsocketBackbone
from workers.envs.fakes import FakeMarkerEnv
from workers.episode.observation import to_policy_observation
from workers.policy.wrapper import IDRWrapper

ROOT = Path(__file__).resolve().parents[3]
KEYS = {"image:agentview": "observation/image", "state": "observation/state", "prompt": "prompt"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


OPENPI_PYTHON = ROOT / ".venv-openpi" / "bin" / "python"
needs_openpi = pytest.mark.skipif(
    not OPENPI_PYTHON.exists(),
    reason="no .venv-openpi (scripts/setup_openpi.sh, run by make setup)",
)


class Server:
    """The fake server (this Python, websockets), or with ``real=True`` the closed-form policy
    served by the openpi-server package in .venv-openpi."""

    def __init__(self, *flags: str, port: int | None = None, real: bool = False) -> None:
        self.port = port or _free_port()
        python, module = (
            (str(OPENPI_PYTHON), "workers.backbones.websocket.fake_server_openpi")
            if real
            else (sys.executable, "workers.backbones.websocket.fake_server")
        )
        self.proc = subprocess.Popen(
            [python, "-m", module, "--port", str(self.port), *flags],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONPATH": str(ROOT)},
        )
        assert self.proc.stdout.readline().strip() == "ready"
        if real:  # it prints before binding: wait until it answers
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                with socket.socket() as s:
                    if s.connect_ex(("127.0.0.1", self.port)) == 0:
                        break
                time.sleep(0.1)

    def stop(self) -> None:
        self.proc.kill()
        self.proc.wait()


@pytest.fixture
def server(request):
    s = Server(*getattr(request, "param", ()))
    yield s
    s.stop()


def test_codec_round_trip_in_openpis_form():
    msg = {
        "observation/image": np.arange(12, dtype=np.uint8).reshape(2, 2, 3),
        "s": np.float32(1.5),
        "prompt": "x",
    }
    raw = codec.unpackb(codec.packb(msg))
    assert np.array_equal(raw["observation/image"], msg["observation/image"])
    assert raw["s"] == np.float32(1.5) and raw["s"].dtype == np.float32 and raw["prompt"] == "x"
    import msgpack

    plain = msgpack.unpackb(codec.packb({"a": np.zeros(2, np.float64)}))
    assert set(plain["a"]) == {b"__ndarray__", b"data", b"dtype", b"shape"}  # openpi's map
    with pytest.raises(ValueError, match="unsupported dtype"):
        codec.packb(np.array([1j]))


@needs_openpi
def test_codec_round_trips_through_openpi_clients_own():
    """Ours packs, openpi_client.msgpack_numpy (its numpy 1.26 venv) unpacks and packs back,
    ours unpacks: the same arrays, dtypes and scalars."""
    msg = {
        "observation/image": np.arange(2 * 4 * 3, dtype=np.uint8).reshape(2, 4, 3),
        "observation/state": np.linspace(-1, 1, 8, dtype=np.float32),
        "noise": np.ones((4, 7), dtype=np.float32),
        "step": np.int64(3),
        "prompt": "pick up the red cube",
    }
    r = subprocess.run(
        [
            str(OPENPI_PYTHON),
            "-m",
            "workers.backbones.websocket.fake_server_openpi",
            "--codec-check",
        ],
        input=codec.packb(msg),
        capture_output=True,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        timeout=60,
    )
    assert r.returncode == 0, r.stderr.decode()[-2000:]
    back = codec.unpackb(r.stdout)
    assert back["prompt"] == msg["prompt"] and back["step"] == 3 and back["step"].dtype == np.int64
    for k in ("observation/image", "observation/state", "noise"):
        assert back[k].dtype == msg[k].dtype and np.array_equal(back[k], msg[k])


@needs_openpi
@pytest.mark.parametrize("flags", [(), ("--batch", "--noise")], ids=["per-row", "batched+noise"])
def test_idr_through_the_real_openpi_server_package(flags):
    server = Server(*flags, real=True)
    try:
        backbone = WebsocketBackbone(port=server.port, key_map=KEYS)
        policy = IDRWrapper(backbone, RefinerConfig(mode="E"))
        raw, obs = _obs(2)
        out = policy.infer(obs, 5)
        m = raw.images["agentview"].astype(np.float64).mean() / 255
        s = raw.state.astype(np.float64).mean()
        assert out.diag.e_img[0] == pytest.approx(2.0 * m * np.sqrt(28), rel=1e-5)
        assert out.diag.e_prop[0] == pytest.approx(0.5 * abs(s) * np.sqrt(28), rel=1e-5)
        assert out.crn is ("--noise" in flags)
        backbone.close()
    finally:
        server.stop()


def _obs(e: int = 0):
    env = FakeMarkerEnv()
    obs = env.reset("reach", e, 0)
    return obs, to_policy_observation(obs, obs.status.instruction)


@pytest.mark.parametrize("server", [(), ("--batch",)], indirect=True, ids=["per-row", "batched"])
def test_idr_effects_through_the_server_equal_the_closed_form(server):
    backbone = WebsocketBackbone(port=server.port, key_map=KEYS)
    policy = IDRWrapper(backbone, RefinerConfig(mode="E"))
    raw, obs = _obs()
    out = policy.infer(obs, 7)
    m = raw.images["agentview"].astype(np.float64).mean() / 255
    s = raw.state.astype(np.float64).mean()
    scale = np.sqrt(4 * 7)  # the norm over the whole (T, D) chunk
    assert out.diag.e_img[0] == pytest.approx(2.0 * m * scale, rel=1e-5)
    assert out.diag.e_prop[0] == pytest.approx(0.5 * abs(s) * scale, rel=1e-5)
    assert out.crn is False and backbone.chunk_len == 4 and backbone.action_dim == 7
    backbone.close()


@pytest.mark.parametrize("server", [("--noise",), ("--noise", "--batch")], indirect=True)
def test_shared_noise_leaves_the_effects_exact_and_is_reproducible(server):
    backbone = WebsocketBackbone(port=server.port, key_map=KEYS)
    policy = IDRWrapper(backbone, RefinerConfig(mode="E"))
    raw, obs = _obs(1)
    a, b = policy.infer(obs, 3), policy.infer(obs, 3)
    m = raw.images["agentview"].astype(np.float64).mean() / 255
    assert a.crn is True and np.array_equal(a.a_base, b.a_base)  # same seed, same noise
    assert a.diag.e_img[0] == pytest.approx(2.0 * m * np.sqrt(28), rel=1e-5)  # noise cancels
    assert not np.array_equal(a.a_base, policy.infer(obs, 4).a_base)
    backbone.close()


def test_an_unreachable_server_is_one_error_within_seconds():
    t0 = time.monotonic()
    with pytest.raises(
        ValueError, match=r"policy server ws://127.0.0.1:\d+ \(backbone.params.host/port\)"
    ):
        WebsocketBackbone.check_params({"port": _free_port(), "timeout_s": 3})
    assert time.monotonic() - t0 < 10


@pytest.mark.parametrize("server", [("--fail-on", "2")], indirect=True)
def test_a_server_traceback_becomes_the_error_in_its_words(server):
    backbone = WebsocketBackbone(port=server.port, key_map=KEYS)
    _, obs = _obs()
    backbone.predict_chunk(obs)
    with pytest.raises(RemoteBackboneError, match="injected failure in the fake policy"):
        backbone.predict_chunk(obs)


def test_a_server_that_dies_mid_episode_fails_the_call_and_the_next_connects_anew():
    server = Server("--exit-on", "2")
    try:
        backbone = WebsocketBackbone(port=server.port, key_map=KEYS, timeout_s=5)
        _, obs = _obs()
        backbone.predict_chunk(obs)
        with pytest.raises(RemoteBackboneError):
            backbone.predict_chunk(obs)  # the episode's error row; the scheduler runs it again
    finally:
        server.stop()
    restarted = Server(port=server.port)
    try:
        assert backbone.predict_chunk(obs).shape == (1, 4, 7)  # a fresh connection
    finally:
        restarted.stop()


def _remote_overrides(port: int) -> list[str]:
    return [
        "tracking.enabled=false",
        "executor.kind=inline",
        "backbone.kind=remote",
        f"backbone.params={{port: {port}, timeout_s: 10, key_map: {{image:agentview: observation/image, state: observation/state, prompt: prompt}}}}",
    ]


def test_the_cli_runs_idr_through_a_policy_server_and_survives_its_crash(tmp_path):
    """The smoke preset's episodes through the fake server; the server dies at its 30th request
    and is started again on its port (as a supervisor would): the episode it was serving is run
    again, every key stored once, no error row."""
    import threading

    from pipeline.execution.runner import execute, plan_run
    from pipeline.planning.config import load_config
    from pipeline.results.store import RunStore

    flags = ("--action-dim", "2", "--horizon", "4")
    server = Server(*flags, "--exit-on", "30")
    stop = threading.Event()

    def supervise() -> None:
        nonlocal server
        server.proc.wait()
        if not stop.is_set():
            server = Server(*flags, port=server.port)

    watcher = threading.Thread(target=supervise, daemon=True)
    watcher.start()
    try:
        cfg = load_config(ROOT / "conf" / "smoke.yaml", _remote_overrides(server.port))
        summary = execute(plan_run(cfg, tmp_path / "run"))
    finally:
        stop.set()
        watcher.join(timeout=20)
        server.stop()
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    assert summary.stored == 12 and summary.errors == 0 and len(eps) == 12
    assert eps.error.isna().all() and (eps.attempt == 2).sum() == 1  # the one it was serving
    assert eps.loc[eps.cell_id == "E", "e_img_mean"].gt(0).all()
    assert eps.loc[eps.cell_id == "baseline", "e_img_mean"].isna().all()


def test_an_unreachable_server_is_refused_before_any_work(tmp_path):
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import ConfigError, load_config

    cfg = load_config(ROOT / "conf" / "smoke.yaml", _remote_overrides(_free_port()))
    with pytest.raises(ConfigError, match=r"policy server ws://127\.0\.0\.1"):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_an_action_dim_that_does_not_fit_the_env_is_refused_naming_both_sides(tmp_path):
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import ConfigError, load_config

    server = Server()  # 7-d actions; the fake marker env takes 2-d ones
    try:
        overrides = [*_remote_overrides(server.port), "backbone.params.action_dim=7"]
        cfg = load_config(ROOT / "conf" / "smoke.yaml", overrides)
        with pytest.raises(
            ConfigError, match=r"env takes 2-d actions, but the policy server ws://"
        ):
            plan_run(cfg, tmp_path / "run")
        # undeclared, a reply of another size than declared is the episode's error, named
        backbone = WebsocketBackbone(port=server.port, key_map=KEYS, action_dim=2)
        with pytest.raises(RemoteBackboneError, match="answered 7-d actions but declared 2"):
            backbone.predict_chunk(_obs()[1])
    finally:
        server.stop()


@needs_openpi
@pytest.mark.slow
def test_the_tabletop_through_the_real_openpi_server_with_its_dry_run(tmp_path):
    """The CLI's pre-flight sends a dry run shaped like the tabletop's observation (two 96 px
    cameras, 8-d state): a 2-d answer is refused naming both sides; a 7-d one runs, and IDR's
    effects are in the rows."""
    from pipeline.execution.runner import execute, plan_run
    from pipeline.planning.config import ConfigError, load_config
    from pipeline.results.store import RunStore

    def cfg(port: int):
        return load_config(
            ROOT / "conf" / "default.yaml",
            [
                "tracking.enabled=false",
                "executor.kind=inline",
                "env.tasks=[pick_color]",
                "episodes_per_task=1",
                "grid=[{mode: [E]}]",
                "idr.tau=7.0",
                "intervention.state_space=raw",  # a served model: interventions on our side
                "backbone.kind=remote",
                "backbone.replan_steps=4",
                f"backbone.params={{port: {port}, key_map: openpi_libero}}",
            ],
        )

    wrong = Server("--action-dim", "2", real=True)
    try:
        with pytest.raises(
            ConfigError, match=r"env takes 7-d actions, but the policy server .* \(4, 2\)"
        ):
            plan_run(cfg(wrong.port), tmp_path / "wrong")
    finally:
        wrong.stop()
    server = Server(real=True)
    try:
        summary = execute(plan_run(cfg(server.port), tmp_path / "run"))
    finally:
        server.stop()
    eps = RunStore(tmp_path / "run").episodes().to_pandas()
    assert summary.stored == 1 and summary.errors == 0 and eps.error.isna().all()
    assert eps.e_img_mean.iloc[0] > 0 and eps.steps.iloc[0] > 0
