"""LIBERO's named protocols: what each pins, what params override, what the env describes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from workers.envs.suites.libero.env import LiberoEnv
from workers.envs.suites.libero.protocol import (
    PROTOCOLS,
    LiberoProtocol,
    quat_to_axis_angle,
    quat_to_axis_angle_f32,
)


def _protocol(name: str, **over) -> LiberoProtocol:
    params = {
        "suites": ("libero_spatial", "libero_object", "libero_goal", "libero_10"),
        "image_size": None,
        "cameras": ("agentview", "wrist"),
        "num_noops": None,
        "max_steps": None,
        "flip_images": True,
        "control_hz": 20.0,
    }
    return LiberoProtocol.from_params(name, **{**params, **over})


def test_openpi_is_the_papers_protocol() -> None:
    p = _protocol("openpi")
    assert dict(p.max_steps) == {
        "libero_spatial": 220,
        "libero_object": 280,
        "libero_goal": 300,
        "libero_10": 520,
    }
    assert (p.image_size, p.image_size_from_checkpoint, p.num_noops, p.replan) == (
        256,
        False,
        10,
        5,
    )
    assert [p.reset_seed(7, e) for e in range(3)] == [7, 7, 7]
    assert not p.float32_state


def test_lerobot_is_lerobot_evals_protocol() -> None:
    p = _protocol("lerobot")
    assert p.max_steps["libero_spatial"] == 280 and p.max_steps["libero_10"] == 520
    # the checkpoint's size (filled in by the pre-flight), lerobot-eval's 360 without one
    assert (p.image_size, p.image_size_from_checkpoint) == (360, True)
    assert p.replan == "chunk"
    assert [p.reset_seed(7, e) for e in range(3)] == [7, 8, 9]
    assert p.float32_state
    assert p.record()["seed"] == "seed + episode"
    # libero_90 has a figure under lerobot only
    assert _protocol("lerobot", suites=["libero_90"]).max_steps == {"libero_90": 400}
    with pytest.raises(
        ValueError, match=r"max_steps\['libero_90'\] must be set: protocol 'openpi'"
    ):
        _protocol("openpi", suites=["libero_90"])


def test_params_override_single_figures_and_are_logged() -> None:
    p = _protocol("lerobot", image_size=128, max_steps={"libero_spatial": 40}, num_noops=0)
    rec = p.record()
    assert rec["name"] == "lerobot" and rec["image_size"] == 128 and rec["num_noops"] == 0
    assert rec["max_steps"]["libero_spatial"] == 40 and rec["max_steps"]["libero_goal"] == 300
    assert not p.image_size_from_checkpoint  # told: the checkpoint no longer decides


def test_unknown_protocol_names_the_valid_ones() -> None:
    with pytest.raises(ValueError, match=r"protocol='lerobot-eval'.*\['openpi', 'lerobot'\]"):
        _protocol("lerobot-eval")
    assert set(PROTOCOLS) == {"openpi", "lerobot"}


def test_describe_gives_cameras_dims_protocol_and_replan_without_a_simulator() -> None:
    io = LiberoEnv.describe(protocol="lerobot", cameras=["agentview"])
    assert io.cameras == ("agentview",) and io.state_dim == 8 and io.action_dim == 7
    assert "image" in io.camera_aliases["agentview"]  # lerobot's LIBERO name for it
    assert io.replan == "chunk" and io.image_size_from_checkpoint
    assert io.protocol["name"] == "lerobot"
    assert LiberoEnv.describe().protocol["name"] == "openpi"  # the default
    with pytest.raises(TypeError):
        LiberoEnv.describe(protocl="lerobot")  # a typo is not silently dropped


def test_float32_axis_angle_agrees_with_float64_within_float32_precision() -> None:
    rng = np.random.default_rng(1)
    for q in rng.normal(size=(200, 4)):
        q /= np.linalg.norm(q)
        np.testing.assert_allclose(
            quat_to_axis_angle_f32(q), quat_to_axis_angle(q), rtol=1e-5, atol=1e-6
        )
    assert quat_to_axis_angle_f32(np.array([0, 0, 0, 1.0])).tolist() == [0, 0, 0]
    half = math.pi / 4
    q = np.array([0.0, 0.0, math.sin(half), math.cos(half)])
    assert quat_to_axis_angle_f32(q).dtype == np.float32
    np.testing.assert_allclose(quat_to_axis_angle_f32(q), [0, 0, math.pi / 2], atol=1e-6)
