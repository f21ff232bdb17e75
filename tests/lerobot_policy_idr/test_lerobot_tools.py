"""lerobot's own tools run the idr policy unchanged: lerobot-eval (its CLI on PushT, its rollout
function on LIBERO), lerobot-rollout on a robot plugin (a FAKE camera arm), and lerobot's async
inference server through its real gRPC service. And the plugin's mode E under lerobot-eval gives
idr-eval's in-actor episodes (``lerobot`` LIBERO protocol) bit for bit, E_img included."""

from __future__ import annotations

import json
import os
import pickle
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from idr_core.sidecar import read_sidecar

from tests.lerobot_policy_idr.conftest import make_idr
from tests.support.lerobot_eval import lerobot_eval_libero
from training.toy_checkpoints import build_act

pytestmark = pytest.mark.slow
BIN = Path(sys.executable).parent
SIZE, STEPS, EPISODES, SEED, TAU = 64, 15, 2, 7, 1e9


def _libero_env() -> dict[str, str]:
    from workers.envs.suites.libero.assets import ensure_config_env
    from workers.rendering import configure_rendering

    ensure_config_env()
    configure_rendering()  # this process's environment: MUJOCO_GL, PYOPENGL_PLATFORM
    return dict(os.environ)


@pytest.fixture(scope="module")
def libero_act(tmp_path_factory) -> Path:
    """ACT with lerobot's LIBERO camera keys (image, image2), 64 px, replanning every 5."""
    return build_act(
        tmp_path_factory.mktemp("libero") / "act",
        image=SIZE,
        cams=("image", "image2"),
        chunk=10,
        n_action_steps=5,
    )


def test_lerobot_eval_cli_runs_the_idr_type_around_a_base_folder(tmp_path) -> None:
    """``lerobot-eval --policy.type=idr --policy.base_policy_path=...`` (no IDR folder), on
    PushT: the type is found by its name in a fresh process and wraps the base it names. (The
    CLI with an IDR folder: test_queue_fed; lerobot-eval's rollout on LIBERO: below.)"""
    base = build_act(
        tmp_path / "act", image=96, state=2, action=2, cams=("image!",), chunk=10,
        n_action_steps=5,
    )  # fmt: skip
    diag = tmp_path / "diag"
    cmd = [
        str(BIN / "lerobot-eval"),
        "--policy.type=idr",
        f"--policy.base_policy_path={base}",
        "--policy.mode=diagnose",
        f"--policy.diagnostics_dir={diag}",
        "--policy.device=cpu",
        "--env.type=pusht",
        "--env.observation_height=96",
        "--env.observation_width=96",
        "--env.episode_length=10",
        "--eval.n_episodes=1",
        "--eval.batch_size=1",
        f"--output_dir={tmp_path / 'eval'}",
        f"--seed={SEED}",
    ]
    env = {**os.environ, "HF_HUB_OFFLINE": "1"}
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    info = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1
    rows = read_sidecar(diag)
    assert list(rows["step"]) == [1, 6]  # 10 steps, a chunk every n_action_steps = 5
    assert (rows["e_img"] > 0).all() and set(rows["mode"]) == {"diagnose"}


def _our_episodes(ckpt: Path, tmp_path: Path) -> tuple[list[list[np.ndarray]], list[list[float]]]:
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import config_from_dict
    from workers.episode.worker import EpisodeWorker

    cfg = config_from_dict(
        {
            "name": "plugin-parity",
            "backbone": {"kind": "lerobot", "params": {"path": str(ckpt)}},
            "env": {
                "suite": "libero",
                "tasks": ["libero_spatial/0"],
                "params": {
                    "protocol": "lerobot",
                    "suites": ["libero_spatial"],
                    "max_steps": {"libero_spatial": STEPS},
                },
            },
            "intervention": {"strategy": "zero", "image_space": "raw", "state_space": "normalized"},
            "episodes_per_task": EPISODES,
            "seed": SEED,
            "grid": [{"mode": ["E"], "tau": [TAU]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
            "output_root": str(tmp_path),
        }
    )
    plan = plan_run(cfg, tmp_path / "run")
    worker = EpisodeWorker(plan.worker_spec)
    actions: list[list[np.ndarray]] = []
    step = worker.env.step

    def recording_step(action):
        actions[-1].append(np.asarray(action, dtype=np.float32).copy())
        return step(action)

    worker.env.step = recording_step
    e_img = []
    try:
        for spec in plan.specs:
            actions.append([])
            result = worker.run_episode(spec)
            assert result.episode.error is None, result.episode.error
            e_img.append([float(s.e_img) for s in result.steps])
    finally:
        worker.close()
    return actions, e_img


@pytest.mark.sim
def test_mode_E_under_lerobot_eval_gives_idr_evals_episodes(libero_act, tmp_path) -> None:
    _libero_env()
    ours, our_e_img = _our_episodes(libero_act, tmp_path)
    folder = make_idr(
        libero_act,
        tmp_path / "idr",
        "--tau",
        str(TAU),
        "--no-clip",
        "--diagnostics-dir",
        str(tmp_path / "diag"),
    )
    recorded, _ = lerobot_eval_libero(folder, steps=STEPS, episodes=EPISODES, seed=SEED, size=SIZE)
    theirs = [e["actions"] for e in recorded]
    assert len(theirs) == len(ours) == EPISODES
    for e, (a, b) in enumerate(zip(theirs, ours, strict=True)):
        assert len(a) == len(b) == STEPS, f"episode {e}"
        for t, (x, y) in enumerate(zip(a, b, strict=True)):
            assert np.array_equal(x, y), f"episode {e} step {t}: {x} vs {y}"
    rows = read_sidecar(tmp_path / "diag")
    plugin_e_img = [list(g["e_img"]) for _, g in rows.groupby("episode", sort=True)]
    assert [len(x) for x in plugin_e_img] == [len(x) for x in our_e_img] == [3, 3]
    assert np.array_equal(
        np.float32(np.concatenate(plugin_e_img)), np.float32(np.concatenate(our_e_img))
    )
    # refined: the gate was on, so these are not the base's actions
    assert (rows["gate"] == 1.0).all() and (rows["e_img"] > 0).all()


def _fake_robot_site(tmp_path: Path) -> Path:
    """The FAKE robot plugin installed as lerobot finds plugins: a package and a dist-info
    named lerobot_robot_* on the subprocess's path."""
    site = tmp_path / "site"
    pkg = site / "lerobot_robot_fake_camera_arm"
    pkg.mkdir(parents=True)
    src = Path(__file__).parents[1] / "doubles" / "fake_robot_plugin.py"
    (pkg / "__init__.py").write_text(src.read_text())
    meta = site / "lerobot_robot_fake_camera_arm-0.0.0.dist-info"
    meta.mkdir()
    (meta / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: lerobot_robot_fake_camera_arm\nVersion: 0.0.0\n"
    )
    return site


def test_lerobot_rollout_drives_a_robot_plugin_with_idr(tmp_path) -> None:
    base = build_act(
        tmp_path / "act", image=64, state=6, action=6, cams=("front",), n_action_steps=5
    )
    folder = make_idr(
        base, tmp_path / "idr", "--tau", "3", "--diagnostics-dir", str(tmp_path / "d")
    )
    log = tmp_path / "actions.jsonl"
    env = dict(os.environ, PYTHONPATH=str(_fake_robot_site(tmp_path)))
    cmd = [
        str(BIN / "lerobot-rollout"),
        "--robot.type=fake_camera_arm",
        f"--robot.action_log={log}",
        f"--robot.calibration_dir={tmp_path / 'calib'}",
        f"--policy.path={folder}",
        "--strategy.type=base",
        "--duration=3",
        "--fps=10",
        "--task=pick up the cube",
        "--play_sounds=false",
    ]
    run = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0 and "Traceback" not in run.stderr, run.stderr[-3000:]
    rows = read_sidecar(tmp_path / "d")
    ticks = len(rows)
    assert ticks >= 3  # ~30 control steps at 10 fps, a chunk every 5
    assert list(rows["step"]) == [1 + 5 * i for i in range(ticks)]  # one row per inference
    assert (rows["wait_ms"] >= rows["inference_ms"]).all() and rows["e_img"].notna().all()
    actions = [json.loads(line) for line in log.read_text().splitlines()]
    policy_steps = int(rows["step"].max()) + 4
    assert len(actions) >= policy_steps  # every policy action reached the robot
    assert all(np.isfinite(list(a.values())).all() for a in actions)


def test_the_async_policy_server_answers_an_idr_chunk(tmp_path) -> None:
    """lerobot's PolicyServer on loopback, its real gRPC service, lerobot's client messages."""
    from concurrent import futures

    import grpc
    from lerobot.async_inference.configs import PolicyServerConfig
    from lerobot.async_inference.helpers import RemotePolicyConfig, TimedObservation
    from lerobot.async_inference.policy_server import PolicyServer
    from lerobot.transport import services_pb2, services_pb2_grpc
    from lerobot.transport.utils import send_bytes_in_chunks
    from lerobot_policy_idr.policy_server import allow_idr, is_loopback

    allow_idr()
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and not is_loopback("0.0.0.0")
    base = build_act(
        tmp_path / "act", image=64, state=6, action=6, cams=("front",), n_action_steps=5
    )
    folder = make_idr(
        base, tmp_path / "idr", "--tau", "3", "--diagnostics-dir", str(tmp_path / "d")
    )
    server = PolicyServer(
        PolicyServerConfig(host="127.0.0.1", port=8080)
    )  # config only; bound below
    grpc_server = grpc.server(futures.ThreadPoolExecutor(max_workers=4))
    services_pb2_grpc.add_AsyncInferenceServicer_to_server(server, grpc_server)
    port = grpc_server.add_insecure_port("127.0.0.1:0")
    grpc_server.start()
    try:
        stub = services_pb2_grpc.AsyncInferenceStub(grpc.insecure_channel(f"127.0.0.1:{port}"))
        stub.Ready(services_pb2.Empty())
        joints = [f"joint{i}.pos" for i in range(6)]
        features = {
            "observation.state": {"dtype": "float32", "shape": (6,), "names": joints},
            "observation.images.front": {
                "dtype": "image",
                "shape": (64, 64, 3),
                "names": ["height", "width", "channels"],
            },
        }
        spec = RemotePolicyConfig(
            policy_type="idr",
            pretrained_name_or_path=str(folder),
            lerobot_features=features,
            actions_per_chunk=5,
            device="cpu",
        )
        stub.SendPolicyInstructions(services_pb2.PolicySetup(data=pickle.dumps(spec)))
        raw = {j: 0.1 * i for i, j in enumerate(joints)}
        raw["front"] = np.full((64, 64, 3), 120, dtype=np.uint8)
        raw["task"] = "pick up the cube"
        obs = TimedObservation(timestamp=0.0, timestep=0, observation=raw, must_go=True)
        stub.SendObservations(
            send_bytes_in_chunks(pickle.dumps(obs), services_pb2.Observation, log_prefix="[test]")
        )
        answer = stub.GetActions(services_pb2.Empty())
        chunk = pickle.loads(answer.data)
    finally:
        grpc_server.stop(None)
    assert len(chunk) == 5
    acts = torch.stack([a.get_action() for a in chunk])
    assert acts.shape == (5, 6) and torch.isfinite(acts).all()
    server.policy.sidecar.flush()
    rows = read_sidecar(tmp_path / "d")
    assert len(rows) == 1 and rows["e_img"].iloc[0] > 0
