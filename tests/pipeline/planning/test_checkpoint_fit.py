"""The pre-flight's matching of a checkpoint with an env, on hand-made descriptions."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.planning.checkpoint_fit import fit_backbone_to_env, resolve_replan
from pipeline.planning.config import ConfigError
from workers.io_spec import ROBOSUITE_CAMERA_ALIASES, EnvIO, PolicyIO


def _env(**over) -> EnvIO:
    base = {
        "cameras": ("agentview", "wrist"),
        "image_size": 256,
        "state_dim": 8,
        "action_dim": 7,
        "camera_aliases": ROBOSUITE_CAMERA_ALIASES,
        "protocol": {"name": "lerobot"},
    }
    return EnvIO(**{**base, **over})


def _policy(**over) -> PolicyIO:
    base = {
        "images": {"image": (3, 256, 256), "image2": (3, 256, 256)},
        "state_dim": 8,
        "action_dim": 7,
        "chunk_len": 10,
        "resizes_images": False,
        "source": "ckpt/config.json (policy type 'act')",
    }
    return PolicyIO(**{**base, **over})


@pytest.mark.parametrize(
    ("keys", "expected"),
    [
        (("image", "image2"), {"agentview": "image", "wrist": "image2"}),  # lerobot's LIBERO
        (("image", "wrist_image"), {"agentview": "image", "wrist": "wrist_image"}),  # openpi's
        (("front", "wrist"), {"agentview": "front", "wrist": "wrist"}),
        (("agentview",), {"agentview": "agentview"}),
    ],
)
def test_known_camera_names_map_without_a_camera_map(keys, expected) -> None:
    policy = _policy(images={k: (3, 256, 256) for k in keys})
    assert fit_backbone_to_env(_env(), policy, None, None).camera_map == expected


def test_an_unknown_camera_name_is_refused_naming_both_sides_and_the_fix() -> None:
    policy = _policy(images={"cam_high": (3, 256, 256)})
    with pytest.raises(ConfigError) as e:
        fit_backbone_to_env(_env(), policy, None, None)
    msg = str(e.value)
    assert "observation.images.cam_high" in msg and "ckpt/config.json" in msg
    assert "['agentview', 'wrist']" in msg and "backbone.params.camera_map" in msg


def test_a_camera_the_env_does_not_render_names_env_cameras() -> None:
    with pytest.raises(ConfigError, match=r"image2.*matches no env camera.*env.params.cameras"):
        fit_backbone_to_env(_env(cameras=("agentview",)), _policy(), None, None)


def test_camera_map_is_checked_against_both_sides() -> None:
    ok = fit_backbone_to_env(_env(), _policy(), None, {"wrist": "image", "agentview": "image2"})
    assert ok.camera_map == {"wrist": "image", "agentview": "image2"}  # unusual, but as told
    with pytest.raises(ConfigError, match=r"names env cameras \['top'\].*\['agentview', 'wrist'\]"):
        fit_backbone_to_env(_env(), _policy(), None, {"top": "image", "wrist": "image2"})
    with pytest.raises(ConfigError, match=r"feeds image keys .*declares .*image2"):
        fit_backbone_to_env(_env(), _policy(), None, {"agentview": "image"})


def test_image_size_comes_from_the_checkpoint_where_the_protocol_leaves_it() -> None:
    policy = _policy(images={"image": (3, 64, 64), "image2": (3, 64, 64)})
    fit = fit_backbone_to_env(
        _env(image_size=360, image_size_from_checkpoint=True), policy, 5, None
    )
    assert fit.image_size == 64 and fit.protocol["image_size"] == 64
    uneven = _policy(images={"image": (3, 64, 64), "image2": (3, 96, 96)})
    with pytest.raises(ConfigError, match="not one square size"):
        fit_backbone_to_env(_env(image_size_from_checkpoint=True), uneven, 5, None)


def test_a_size_mismatch_is_refused_unless_the_policy_resizes() -> None:
    policy = _policy(images={"image": (3, 224, 224), "image2": (3, 224, 224)})
    with pytest.raises(ConfigError) as e:
        fit_backbone_to_env(_env(), policy, None, None)
    msg = str(e.value)
    assert "256 px" in msg and "(3, 224, 224)" in msg and "env.params.image_size=224" in msg
    resizing = _policy(images=policy.images, resizes_images=True)  # pi0.5: any size fits
    assert fit_backbone_to_env(_env(), resizing, None, None).image_size is None


def test_a_camera_that_is_not_square_is_matched_on_height_and_width() -> None:
    env = _env(cameras=("top",), image_size=480, camera_sizes={"top": (480, 640)})
    assert env.hw_of("top") == (480, 640) and env.size_label("top") == "480x640"
    fits = _policy(images={"top": (3, 480, 640)})
    assert fit_backbone_to_env(env, fits, None, None).camera_map == {"top": "top"}
    square = _policy(images={"top": (3, 480, 480)})
    with pytest.raises(ConfigError, match=r"'top' at 480x640 px.*\(3, 480, 480\)"):
        fit_backbone_to_env(env, square, None, None)
    transposed = _policy(images={"top": (3, 640, 480)})  # height and width are not swapped
    with pytest.raises(ConfigError, match="480x640"):
        fit_backbone_to_env(env, transposed, None, None)


@pytest.mark.parametrize(
    ("over", "message"),
    [
        ({"state_dim": 9}, r"state: the env gives a 8-d state, but .*observation.state \(9,\)"),
        ({"action_dim": 14}, r"action: the env takes 7-d actions, but .*action \(14,\)"),
        ({"images": {"image": (1, 256, 256)}}, "RGB"),
    ],
)
def test_dims_that_do_not_fit_are_refused(over, message) -> None:
    with pytest.raises(ConfigError, match=message):
        fit_backbone_to_env(_env(), _policy(**over), None, None)


def test_a_policy_without_state_fits_any_state() -> None:
    assert fit_backbone_to_env(_env(), _policy(state_dim=None), None, None).camera_map


def test_replan_rule() -> None:
    env, policy = _env(replan="chunk"), _policy(chunk_len=10)
    assert resolve_replan(None, env, policy) == 10  # the protocol's rule, the checkpoint's n
    assert resolve_replan(3, env, policy) == 3  # the config wins
    assert resolve_replan(None, _env(replan=5), policy) == 5
    assert resolve_replan(None, _env(), policy) == 4  # no rule, a base of unknown training
    trained = _policy(chunk_len=10, trained_on_data=True)  # a lerobot checkpoint
    assert resolve_replan(None, _env(), trained) == 10  # its n_action_steps, as the plugin runs
    assert resolve_replan(None, None, trained) == 10
    assert resolve_replan(None, None, None) == 4
    assert resolve_replan("chunk", None, None) == "chunk"  # the backbone's chunk at run time
    fit = fit_backbone_to_env(env, policy, None, None)
    assert fit.replan_steps == 10 and fit.protocol["replan"] == 10


def test_an_env_without_a_protocol_logs_none_and_same_names_need_no_note() -> None:
    """The tabletop suite: no protocol to log, cameras named as the env names them."""
    policy = _policy(images={"agentview": (3, 256, 256), "wrist": (3, 256, 256)})
    fit = fit_backbone_to_env(_env(protocol={}), policy, None, None)
    assert fit.protocol == {} and fit.notes == () and fit.replan_steps == 4
    assert fit.camera_map == {"agentview": "agentview", "wrist": "wrist"}
    lerobot = fit_backbone_to_env(_env(replan="chunk"), _policy(), None, None)
    assert lerobot.protocol == {"name": "lerobot", "replan": 10}
    assert lerobot.notes == (
        "camera_map {'agentview': 'image', 'wrist': 'image2'} by the checkpoint's camera names",
    )


@pytest.mark.parametrize(
    "where", ["intervention.state_space=normalized", "grid=[{image_space: [raw, normalized]}]"]
)
def test_a_space_the_backbone_cannot_intervene_in_is_refused_before_work(tmp_path, where):
    """The wrapper's check, for every cell, in the pre-flight (was an error row per episode)."""
    from pathlib import Path

    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import load_config

    conf = Path(__file__).resolve().parents[3] / "conf" / "smoke.yaml"
    cfg = load_config(conf, [where, "tracking.enabled=false"])
    with pytest.raises(
        ConfigError, match=r"_space='normalized' is not supported by backbone 'fake_marker'"
    ):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_under_lerobots_protocol_the_run_says_its_torch_threads(monkeypatch) -> None:
    """lerobot-eval runs torch's default threads; an episode equals its episodes bit for bit
    only with as many (a float reduction splits by thread): the pre-flight says which."""
    from pipeline.planning.checkpoint_fit import Fit, with_thread_note
    from pipeline.planning.config import load_config

    monkeypatch.setenv("OMP_NUM_THREADS", "4")
    conf = Path(__file__).resolve().parents[3] / "conf" / "smoke.yaml"
    fit = Fit(4, protocol={"name": "lerobot"})
    one = with_thread_note(fit, load_config(conf, ["executor.torch_threads=1"]))
    assert one.protocol["torch_threads"] == 1
    assert "torch threads 1 per actor, lerobot-eval runs 4 here" in one.notes[-1]
    assert "executor.torch_threads=4" in one.notes[-1]
    four = with_thread_note(fit, load_config(conf, ["executor.torch_threads=4"]))
    assert four.notes[-1].startswith("torch threads 4, as lerobot-eval runs here")
    other = with_thread_note(Fit(4, protocol={"name": "openpi"}), load_config(conf))
    assert other.notes == () and "torch_threads" not in other.protocol


@pytest.mark.parametrize(
    ("over", "what"), [({"images": {}}, "no image"), ({"state_dim": None}, "no state")]
)
def test_counterfactual_modes_need_an_image_and_a_state(over, what) -> None:
    """diagnose / E / F intervene on both; a checkpoint without one runs baseline only."""
    from pipeline.planning.checkpoint_fit import check_inputs_for_modes
    from pipeline.planning.config import load_config

    conf = Path(__file__).resolve().parents[3] / "conf" / "smoke.yaml"
    cfg = load_config(conf, ["tracking.enabled=false"])
    with pytest.raises(
        ConfigError, match=rf"grid: mode E intervenes .* reads {what}; .*mode baseline only"
    ):
        check_inputs_for_modes(cfg, _policy(**over))
    baseline = load_config(conf, ["tracking.enabled=false", "grid=[{mode: [baseline]}]"])
    check_inputs_for_modes(baseline, _policy(**over))  # baseline runs no counterfactual
    check_inputs_for_modes(cfg, _policy())
    # a policy server declares neither: nothing to refuse on
    check_inputs_for_modes(cfg, _policy(**over, declares_inputs=False))


@pytest.mark.parametrize(
    ("mode", "over", "words"),
    [
        ("ensemble", [], r"'ensemble' averages chunks .*'tiny_vla'.* is deterministic"),
        (
            "pcd",
            [
                "env.suite=tests.doubles.envs:NoHiddenRenderMarkerEnv",
                "env.tasks=[reach]",
                "env.params={}",
            ],
            r"'pcd' contrasts .* suite 'tests.doubles.envs:NoHiddenRenderMarkerEnv' does not",
        ),
    ],
)
def test_a_method_the_base_or_suite_cannot_run_is_refused_before_any_episode(
    tmp_path, mode, over, words
) -> None:
    """Ensembling a deterministic policy (the default's tiny VLA), the object-hidden contrast
    on a suite that renders no such image: one message naming the method, base or suite, why."""
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import load_config

    conf = Path(__file__).resolve().parents[3] / "conf" / "default.yaml"
    cfg = load_config(
        conf, [f"grid=[{{mode: [diagnose, {mode}]}}]", "tracking.enabled=false", *over]
    )
    with pytest.raises(ConfigError, match=words):
        plan_run(cfg, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_temporal_ensembling_needs_a_base_with_chunks() -> None:
    from pipeline.planning.checkpoint_fit import check_methods
    from pipeline.planning.config import load_config

    conf = Path(__file__).resolve().parents[3] / "conf" / "smoke.yaml"
    cfg = load_config(conf, ["tracking.enabled=false", "grid=[{mode: [baseline, temporal]}]"])
    with pytest.raises(ConfigError, match=r"cell 'temporal': mode 'temporal' .* one action"):
        check_methods(cfg, _policy(chunk_len=1))
    check_methods(cfg, _policy(chunk_len=8))


def test_centered_do_s_is_recorded_and_refused_for_a_checkpoint_without_a_state_mean(
    tmp_path,
) -> None:
    """The default do(S) is about the base's dataset mean: the run records the values and
    their file; a trained checkpoint whose files hold none is refused before any episode,
    naming the field and its other values; a base without data (a fake) is centered at zero."""
    import json
    import shutil

    from pipeline.execution.runner import plan_run
    from pipeline.planning.checkpoint_fit import state_center
    from pipeline.planning.config import load_config

    conf = Path(__file__).resolve().parents[3] / "conf"
    ckpt = Path(__file__).resolve().parents[3] / "checkpoints" / "tiny_vla"
    over = ["tracking.enabled=false", "intervention.state_space=centered", "episodes_per_task=1"]
    plan = plan_run(load_config(conf / "default.yaml", over), tmp_path / "run")
    center = plan.fit.record()["do_state_center"]
    assert len(center["values"]) == 8 and center["source"].endswith(".safetensors")
    broken = tmp_path / "no_mean"
    shutil.copytree(ckpt, broken)
    pre = json.loads((broken / "policy_preprocessor.json").read_text())
    for step in pre["steps"]:
        step.pop("state_file", None)
    (broken / "policy_preprocessor.json").write_text(json.dumps(pre))
    cfg = load_config(conf / "default.yaml", [*over, f"backbone.params.path={broken}"])
    with pytest.raises(ConfigError, match=r"intervention.state_space=centered .*raw or normalized"):
        plan_run(cfg, tmp_path / "refused")
    assert not (tmp_path / "refused").exists()
    smoke = load_config(conf / "smoke.yaml", ["tracking.enabled=false"])  # fake: zero
    assert state_center(smoke, None) is None  # smoke sets raw: nothing centered
    fake = load_config(
        conf / "smoke.yaml", ["tracking.enabled=false", "intervention.state_space=centered"]
    )
    assert state_center(fake, None)["values"] is None
