"""The remote backbone against a fake policy server speaking openpi's websocket protocol
(another process): the codec, IDR's three passes with exact effects, noise, faults."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from workers.backbones.remote import codec
from workers.backbones.remote.client import RemoteBackbone, RemoteBackboneError
from workers.envs.fakes import FakeMarkerEnv
from workers.idr import IDRConfig
from workers.idr_policy import IDRPolicy
from workers.observation import to_policy_observation

ROOT = Path(__file__).resolve().parents[3]
KEYS = {"image:agentview": "observation/image", "state": "observation/state", "prompt": "prompt"}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Server:
    def __init__(self, *flags: str, port: int | None = None) -> None:
        self.port = port or _free_port()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "tests.doubles.openpi_server", "--port", str(self.port), *flags],
            cwd=ROOT,
            stdout=subprocess.PIPE,
            text=True,
        )
        assert self.proc.stdout.readline().strip() == "ready"

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


def test_codec_matches_openpi_client_where_installed():
    msgpack_numpy = pytest.importorskip("openpi_client.msgpack_numpy")
    msg = {"a": np.arange(6, dtype=np.float32).reshape(2, 3), "b": np.int64(3)}
    for theirs_pack, ours_unpack in (
        (msgpack_numpy.packb, codec.unpackb),
        (codec.packb, msgpack_numpy.unpackb),
    ):
        got = ours_unpack(theirs_pack(msg))
        assert np.array_equal(got["a"], msg["a"]) and got["b"] == 3


def _obs(e: int = 0):
    env = FakeMarkerEnv()
    obs = env.reset("reach", e, 0)
    return obs, to_policy_observation(obs, env.instruction)


@pytest.mark.parametrize("server", [(), ("--batch",)], indirect=True, ids=["per-row", "batched"])
def test_idr_effects_through_the_server_equal_the_closed_form(server):
    backbone = RemoteBackbone(port=server.port, key_map=KEYS)
    policy = IDRPolicy(backbone)
    policy.set_config(IDRConfig(mode="E"))
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
    backbone = RemoteBackbone(port=server.port, key_map=KEYS)
    policy = IDRPolicy(backbone)
    policy.set_config(IDRConfig(mode="E"))
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
        RemoteBackbone.check_params({"port": _free_port(), "timeout_s": 3})
    assert time.monotonic() - t0 < 10


@pytest.mark.parametrize("server", [("--fail-on", "2")], indirect=True)
def test_a_server_traceback_becomes_the_error_in_its_words(server):
    backbone = RemoteBackbone(port=server.port, key_map=KEYS)
    _, obs = _obs()
    backbone.predict_chunk(obs)
    with pytest.raises(RemoteBackboneError, match="injected failure in the fake policy"):
        backbone.predict_chunk(obs)


def test_a_server_that_dies_mid_episode_fails_the_call_and_the_next_connects_anew():
    server = Server("--exit-on", "2")
    try:
        backbone = RemoteBackbone(port=server.port, key_map=KEYS, timeout_s=5)
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

    from pipeline.config import load_config
    from pipeline.runner import execute, plan_run
    from pipeline.store import RunStore

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
    from pipeline.config import ConfigError, load_config
    from pipeline.runner import plan_run

    cfg = load_config(ROOT / "conf" / "smoke.yaml", _remote_overrides(_free_port()))
    with pytest.raises(ConfigError, match=r"policy server ws://127\.0\.0\.1"):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()
