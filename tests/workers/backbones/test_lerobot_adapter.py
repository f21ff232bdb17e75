"""The lerobot adapter on real lerobot policies (ACT, Diffusion with DDIM) built offline."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig

from pipeline.planning.config import ConfigError
from training.toy_checkpoints import build_act, build_diffusion
from workers.backbones.base import Observation
from workers.policy.wrapper import IDRWrapper

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def ckpts(tmp_path_factory):
    root = tmp_path_factory.mktemp("ckpt")
    return {"act": build_act(root / "act"), "diffusion": build_diffusion(root / "diffusion")}


def _obs(b: int = 2, seed: int = 0) -> Observation:
    g = torch.Generator().manual_seed(seed)
    return Observation(
        {"agentview": torch.rand(b, 3, 64, 64, generator=g)},
        0.5 + torch.rand(b, 8, generator=g),
        [f"task {i}" for i in range(b)],
    )


def _backbone(path):
    from workers.backbones.lerobot import LerobotBackbone

    return LerobotBackbone(str(path))


def test_act_loads_with_processors_and_predicts_chunks(ckpts) -> None:
    bb = _backbone(ckpts["act"])
    assert bb.crn_mode == "deterministic" and bb.can_batch and bb.chunk_len == 10
    assert bb.cameras == ("agentview",) and bb.state_dim == 8 and bb.action_dim == 7
    out = bb.predict_chunk(_obs(3))
    assert out.shape == (3, 10, 7) and torch.isfinite(out).all()
    # the postprocessor unnormalized: a constant model output would be mean + std * x
    assert out.dtype == torch.float32


def test_a_checkpoint_trained_on_a_gpu_runs_on_the_cpu(ckpts, tmp_path) -> None:
    """Saved on a CUDA machine, a checkpoint's config and device step name cuda: the device
    step runs where the policy runs, as lerobot-eval overrides it."""
    import shutil

    gpu = tmp_path / "act_gpu"
    shutil.copytree(ckpts["act"], gpu)
    for name in ("config.json", "policy_preprocessor.json"):
        text = (gpu / name).read_text()
        (gpu / name).write_text(re.sub(r'"device": "cpu"', '"device": "cuda"', text))
    assert '"device": "cuda"' in (gpu / "policy_preprocessor.json").read_text()
    bb = _backbone(gpu)
    assert str(bb.device) == "cpu"
    assert torch.equal(bb.predict_chunk(_obs(2)), _backbone(ckpts["act"]).predict_chunk(_obs(2)))


@pytest.mark.parametrize("name", ["act", "diffusion"])
def test_batched_equals_sequential(ckpts, name) -> None:
    bb = _backbone(ckpts[name])
    cfg = RefinerConfig(mode="E", tau=1e9)
    a = IDRWrapper(bb, cfg, batched=True).infer(_obs(2), step_seed=3)
    b = IDRWrapper(bb, cfg, batched=False).infer(_obs(2), step_seed=3)
    for k in ("a_base", "a_no_img", "a_no_prop", "action"):
        torch.testing.assert_close(getattr(a, k), getattr(b, k), rtol=1e-4, atol=1e-4)
    assert a.diag.e_img.min() > 0 and a.diag.e_prop.min() > 0  # both modalities matter


def test_crn_with_diffusion(ckpts) -> None:
    bb = _backbone(ckpts["diffusion"])
    assert bb.crn_mode == "shared_noise"
    noise = bb.make_noise(2, seed=11)
    assert noise.shape == (2, 8, 7)
    obs = _obs(2)
    same = [bb.predict_chunk(obs, noise) for _ in range(2)]
    assert torch.equal(same[0], same[1])  # shared noise, identical inputs: delta exactly 0
    independent = [bb.predict_chunk(obs) for _ in range(2)]
    assert (independent[0] - independent[1]).abs().max() > 1e-3
    # in the wrapper's batched 3B forward, the three thirds get the same noise rows
    seen = []
    orig = bb.policy.predict_action_chunk
    bb.policy.predict_action_chunk = lambda batch, noise=None: (
        seen.append(noise) or orig(batch, noise=noise)
    )
    IDRWrapper(bb, RefinerConfig(), batched=True).infer(obs, step_seed=5)
    (n,) = seen
    assert torch.equal(n[:2], n[2:4]) and torch.equal(n[:2], n[4:])


def _record_step(pipeline, index):
    from lerobot.lerobot_types import TransitionKey

    seen = []

    def hook(i, transition):
        if i == index:
            obs = transition[TransitionKey.OBSERVATION]
            seen.append({k: v.clone() for k, v in obs.items() if torch.is_tensor(v)})

    pipeline.register_after_step_hook(hook)
    return seen


def test_state_zeroed_after_the_normalizer_by_default(ckpts) -> None:
    bb = _backbone(ckpts["act"])
    norm = bb._normalizer_index
    seen = _record_step(bb.pre, norm)
    pol = IDRWrapper(
        bb,
        RefinerConfig(mode="diagnose"),
        InterventionConfig(state_space="normalized"),
        batched=True,
    )
    obs = _obs(2)
    pol.infer(obs)
    state = seen[-1]["observation.state"]  # after normalization, rows: factual, no-img, no-prop
    assert state.shape == (6, 8)
    assert torch.equal(
        state[4:], torch.zeros(2, 8)
    )  # do(S): zero in normalized space (= dataset mean)
    assert (state[:4].abs() > 0).all()
    torch.testing.assert_close(state[0:2], state[2:4])  # do(V) leaves the state alone
    images = seen[-1]["observation.images.agentview"]
    # do(V) zeroed the raw image: after MEAN_STD normalization black is (0 - 0.4) / 0.2
    torch.testing.assert_close(images[2:4], torch.full_like(images[2:4], -2.0))


def test_raw_state_space_zeroes_before_the_pipeline(ckpts) -> None:
    bb = _backbone(ckpts["act"])
    seen = _record_step(bb.pre, bb._normalizer_index)
    pol = IDRWrapper(
        bb, RefinerConfig(mode="diagnose"), InterventionConfig(state_space="raw"), batched=True
    )
    pol.infer(_obs(2))
    stats = json.loads((Path(ckpts["act"]) / "policy_preprocessor.json").read_text())
    assert stats  # saved processors were loaded from the checkpoint
    state = seen[-1]["observation.state"]
    # raw zero -> (0 - mean) / std after normalization: not zero
    assert (state[4:].abs() > 1e-3).any() and torch.allclose(state[4], state[5])


def test_centered_do_s_is_the_saved_dataset_mean_for_every_normalizer(ckpts) -> None:
    """do(S) under ``centered`` (the default) feeds the base its dataset mean state, read the
    same from the saved files (the pre-flight, torch-free) and the loaded normalizer: under
    MEAN_STD that is ``normalized``'s zero bit for bit, under MIN_MAX (Diffusion) it is not the
    middle of the range that ``normalized`` gives."""
    from workers.backbones.lerobot.checkpoint import policy_io

    for kind, mode in (("act", "MEAN_STD"), ("diffusion", "MIN_MAX")):
        bb = _backbone(ckpts[kind])
        io = policy_io(Path(ckpts[kind]))
        assert io.state_mean is not None and io.state_mean_source.endswith(".safetensors")
        assert np.array_equal(np.asarray(io.state_mean, dtype=np.float32), bb.state_mean)
        seen = _record_step(bb.pre, bb._normalizer_index)
        after = {}
        for space in ("centered", "normalized"):
            iv = InterventionConfig(state_space=space)
            IDRWrapper(bb, RefinerConfig(mode="diagnose"), iv, batched=True).infer(_obs(2))
            after[space] = seen[-1]["observation.state"][4:]  # rows: factual, no-img, no-prop
        _, no_prop = IDRWrapper(bb, RefinerConfig(mode="diagnose")).counterfactuals(_obs(2))
        assert np.array_equal(np.asarray(no_prop.state), np.stack([bb.state_mean] * 2))
        same = torch.equal(after["centered"], after["normalized"])
        assert same == (mode == "MEAN_STD"), kind


def test_chunk_and_replan_bookkeeping(tmp_path) -> None:
    """An episode on the fake env with a real ACT: inference every replan_steps control steps."""
    ckpt = build_act(tmp_path / "act2", image=32, state=2, action=2, chunk=10)
    from workers.envs.factory import suite_tasks
    from workers.episode.rows import EpisodeSpec, WorkerSpec
    from workers.episode.worker import EpisodeWorker

    w = EpisodeWorker(WorkerSpec("lerobot", {"path": str(ckpt)}, "fake_marker", {}, replan_steps=3))
    (reach,) = [t for t in suite_tasks("fake_marker", {}) if t.task_id == "reach"]
    res = w.run_episode(
        EpisodeSpec("r", "E", RefinerConfig(tau=1e9), InterventionConfig(), reach, 0, 0, "lerobot")
    )
    assert res.episode.error is None
    steps = [s.step for s in res.steps]
    n = res.episode.steps
    assert steps == list(range(0, n, 3)) and len(steps) == -(-n // 3)
    assert all(len(s.action_final) == 2 for s in res.steps)
    # ACT's head is deterministic: no noise to share, and the row says so
    assert res.episode.crn is False


@pytest.mark.parametrize(
    ("setup", "pattern"),
    [
        (lambda p: p / "missing", r"does not exist"),
        (
            lambda p: (p / "empty").mkdir() or p / "empty",
            r"is not a lerobot policy: no config.json",
        ),
    ],
)
def test_bad_checkpoint_paths(tmp_path, setup, pattern) -> None:
    from workers.backbones.lerobot import check_checkpoint

    with pytest.raises(ValueError, match=pattern):
        check_checkpoint(str(setup(tmp_path)))


def test_pickled_weights_are_refused(ckpts, tmp_path) -> None:
    import shutil

    from workers.backbones.lerobot import check_checkpoint

    bad = tmp_path / "pickled"
    shutil.copytree(ckpts["act"], bad)
    (bad / "model.safetensors").rename(bad / "pytorch_model.bin")
    with pytest.raises(ValueError, match=r"pickled weights are refused"):
        check_checkpoint(str(bad))


def _broken_copy(src: Path, dst: Path, how: str) -> Path:
    import json
    import pickle
    import shutil

    shutil.copytree(src, dst)
    cfg, weights = dst / "config.json", dst / "model.safetensors"
    if how == "unknown type":
        cfg.write_text(json.dumps({**json.loads(cfg.read_text()), "type": "no_such_policy"}))
    elif how == "config is a number":
        cfg.write_text("5")
    elif how == "truncated weights":
        weights.write_bytes(weights.read_bytes()[: weights.stat().st_size // 2])
    elif how == "pickle renamed":
        weights.write_bytes(pickle.dumps({"weight": [1.0, 2.0]}))
    return dst


@pytest.mark.parametrize(
    ("how", "pattern"),
    [
        ("unknown type", r"policy type 'no_such_policy' is not one lerobot knows; known: .*'act'"),
        ("config is a number", r"config.json holds a int, not an object"),
        ("truncated weights", r"model.safetensors is not a complete safetensors file"),
        ("pickle renamed", r"model.safetensors is not a complete safetensors file"),
    ],
)
def test_broken_checkpoints_are_refused_before_loading(ckpts, tmp_path, how, pattern) -> None:
    """What the driver checks before any actor starts: the header, never the tensors."""
    from workers.backbones.factory import check_backbone

    bad = _broken_copy(Path(ckpts["act"]), tmp_path / "bad", how)
    with pytest.raises(ValueError, match=pattern):
        check_backbone("lerobot", {"path": str(bad)})


def test_a_hub_id_is_refused_unless_downloads_are_allowed() -> None:
    from workers.backbones.lerobot import check_checkpoint

    with pytest.raises(ValueError, match=r"looks like a hub id: not downloadable here"):
        check_checkpoint("lerobot/pi05_libero")
    assert check_checkpoint("lerobot/pi05_libero", allow_download=True) is None


def test_camera_and_shape_mismatch_name_both_sides(ckpts) -> None:
    from workers.backbones.lerobot import LerobotBackbone

    with pytest.raises(
        ValueError,
        match=r"camera_map=.*policy image keys \['observation.images.top'\].*declares \['observation.images.agentview'\]",
    ):
        LerobotBackbone(str(ckpts["act"]), camera_map={"agentview": "top"})
    bb = _backbone(ckpts["act"])
    obs = Observation({"agentview": torch.rand(1, 3, 32, 32)}, torch.rand(1, 8), ["x"])
    with pytest.raises(
        ValueError,
        match=r"gives images \(3, 32, 32\).*expects \(3, 64, 64\): set env.params.image_size",
    ):
        bb.predict_chunk(obs)
    obs = Observation({"agentview": torch.rand(1, 3, 64, 64)}, torch.rand(1, 5), ["x"])
    with pytest.raises(
        ValueError, match=r"env state has 5 dims, policy 'observation.state' expects 8"
    ):
        bb.predict_chunk(obs)


def test_runner_refuses_a_missing_checkpoint_before_work(tmp_path) -> None:
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import ConfigError, load_config

    conf = Path(__file__).resolve().parents[3] / "conf" / "smoke.yaml"
    cfg = load_config(
        conf, ["backbone.kind=lerobot", f"backbone.params={{path: {tmp_path / 'nope'}}}"]
    )
    with pytest.raises(ConfigError, match=r"backbone.params.path=.*does not exist"):
        plan_run(cfg, tmp_path / "run")
    assert np.True_


def test_policy_io_reads_config_json_only(ckpts, tmp_path) -> None:
    from workers.backbones.lerobot.adapter import LerobotBackbone
    from workers.backbones.lerobot.checkpoint import policy_io

    io = policy_io(ckpts["act"])
    assert dict(io.images) == {"agentview": (3, 64, 64)}
    assert (io.state_dim, io.action_dim, io.chunk_len, io.resizes_images) == (8, 7, 10, False)
    assert policy_io(ckpts["diffusion"]).chunk_len == 4  # its n_action_steps
    assert LerobotBackbone.describe({"path": str(ckpts["act"]), "chunk_len": 3}).chunk_len == 3
    assert LerobotBackbone.describe({"path": "lerobot/x", "allow_download": True}) is None
    broken = tmp_path / "broken"
    broken.mkdir()
    for f in ckpts["act"].iterdir():
        (broken / f.name).write_bytes(f.read_bytes())
    cfg = json.loads((broken / "config.json").read_text())
    cfg["input_features"]["observation.state"] = {"type": "STATE"}
    (broken / "config.json").write_text(json.dumps(cfg))
    with pytest.raises(ValueError, match=r"'observation.state' has no valid shape"):
        policy_io(broken)


def _libero_argv(ckpt: Path, out: Path, *extra: str) -> list[str]:
    return [
        "run",
        "conf/libero_smoke.yaml",
        "--out",
        str(out),
        "backbone.kind=lerobot",
        f"backbone.params={{path: {ckpt}}}",
        "env.params={protocol: lerobot, suites: [libero_spatial]}",
        "env.tasks=[libero_spatial/0]",
        "executor.kind=inline",
        "tracking.enabled=false",
        *extra,
    ]


@pytest.mark.parametrize(
    ("build", "message"),
    [
        ({"cams": ("image", "cam_high")}, r"reads observation.images.cam_high, which matches no"),
        ({"cams": ("image", "image2"), "state": 9}, r"state: the env gives a 8-d state.*\(9,\)"),
        ({"cams": ("image",), "action": 14}, r"action: the env takes 7-d actions.*\(14,\)"),
    ],
)
def test_a_checkpoint_that_cannot_fit_libero_is_refused_before_work(
    tmp_path, capsys, monkeypatch, build, message
) -> None:
    """The pre-flight reads config.json on the driver: exit 2, one message naming both sides,
    no run dir, no simulator (LIBERO's tables only)."""
    from pipeline.cli import main

    monkeypatch.chdir(Path(__file__).resolve().parents[3])
    ckpt = build_act(tmp_path / "ckpt", **build)
    out = tmp_path / "run"
    assert main(_libero_argv(ckpt, out)) == 2
    err = capsys.readouterr().err
    assert err.count("idr-eval: error:") == 1 and "Traceback" not in err
    assert re.search(message, err), err
    assert not out.exists()


def test_the_preflight_takes_cameras_size_and_replan_from_the_checkpoint(tmp_path) -> None:
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import load_config

    root = Path(__file__).resolve().parents[3]
    ckpt = build_act(tmp_path / "ckpt", image=96, cams=("image", "image2"), n_action_steps=6)
    argv = _libero_argv(ckpt, tmp_path / "run")
    cfg = load_config(root / argv[1], argv[4:])
    plan = plan_run(cfg, tmp_path / "run")
    assert plan.worker_spec.backbone_params["camera_map"] == {
        "agentview": "image",
        "wrist": "image2",
    }
    assert plan.worker_spec.env_params["image_size"] == 96
    assert plan.worker_spec.replan_steps == 6 and plan.cfg.backbone.replan_steps == 6
    assert plan.fit.protocol["name"] == "lerobot" and plan.fit.protocol["image_size"] == 96
    # told otherwise: the config wins where it speaks, and a size that does not fit is refused
    cfg = load_config(root / argv[1], [*argv[4:], "backbone.replan_steps=2"])
    assert plan_run(cfg, tmp_path / "run2").worker_spec.replan_steps == 2
    sized = "env.params={protocol: lerobot, suites: [libero_spatial], image_size: 128}"
    bad = [sized if a.startswith("env.params=") else a for a in argv[4:]]
    with pytest.raises(ConfigError, match=r"renders .* at 128 px.*image_size=96"):
        plan_run(load_config(root / argv[1], bad), tmp_path / "run3")


def test_a_policy_that_trains_at_test_time_is_refused(tmp_path) -> None:
    """lerobot-policy-act-ttt (a real plugin: ACT whose backbone takes optimizer steps on what
    it sees, at inference too): the first chunk is refused, naming why."""
    from training.toy_checkpoints import build_act_ttt
    from workers.backbones.lerobot import LerobotBackbone

    backbone = LerobotBackbone(str(build_act_ttt(tmp_path / "ttt")))
    obs = Observation({"agentview": torch.rand(1, 3, 64, 64)}, torch.rand(1, 8), ["pick"])
    with pytest.raises(ValueError, match="changed its own weights during predict_action_chunk"):
        backbone.predict_chunk(obs)
