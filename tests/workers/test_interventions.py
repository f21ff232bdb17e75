"""Interventions: what each strategy produces, on numpy and torch."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from idr_core.interventions import STRATEGIES, InterventionConfig, intervene, intervene_about


@pytest.mark.parametrize("lib", ["numpy", "torch"])
def test_zero_is_all_zero_same_shape_and_dtype(lib) -> None:
    x = np.random.default_rng(0).uniform(size=(2, 3, 8, 8)).astype(np.float32)
    x = torch.from_numpy(x) if lib == "torch" else x
    out = intervene(x, "zero")
    assert out.shape == x.shape and out.dtype == x.dtype
    assert float(abs(out).sum()) == 0.0
    assert float(abs(x).sum()) > 0  # the input is untouched


@pytest.mark.parametrize("lib", ["numpy", "torch"])
def test_mean_is_the_per_sample_mean(lib) -> None:
    x = np.stack([np.full((3, 4), 2.0), np.arange(12.0).reshape(3, 4)]).astype(np.float32)
    xx = torch.from_numpy(x) if lib == "torch" else x
    out = np.asarray(intervene(xx, "mean"))
    np.testing.assert_allclose(out[0], 2.0)
    np.testing.assert_allclose(out[1], 5.5)


def test_mean_of_uint8_image_rounds() -> None:
    x = np.array([[[0, 255]], [[10, 11]]], dtype=np.uint8)
    out = intervene(x, "mean")
    assert out.dtype == np.uint8
    np.testing.assert_array_equal(out[:, 0], [[128, 128], [10, 10]])


@pytest.mark.parametrize("lib", ["numpy", "torch"])
def test_gaussian_noise_is_half_the_std_and_seeded(lib) -> None:
    rng = np.random.default_rng(1)
    x = (rng.normal(size=(2, 20000)) * np.array([[1.0], [4.0]])).astype(np.float64)
    xx = torch.from_numpy(x) if lib == "torch" else x
    a = np.asarray(intervene(xx, "gaussian", seed=3))
    b = np.asarray(intervene(xx, "gaussian", seed=3))
    c = np.asarray(intervene(xx, "gaussian", seed=4))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    noise_std = (a - x).std(axis=1)
    np.testing.assert_allclose(noise_std, 0.5 * x.std(axis=1), rtol=0.03)


def test_gaussian_refuses_integer_input() -> None:
    with pytest.raises(ValueError, match="floating-point"):
        intervene(np.zeros((1, 4), dtype=np.uint8), "gaussian")


def test_unknown_strategy_names_allowed_values() -> None:
    with pytest.raises(
        ValueError,
        match=r"strategy='blur' is unknown; allowed values: \('zero', 'mean', 'gaussian'\)",
    ):
        intervene(np.zeros((1, 2)), "blur")
    assert STRATEGIES == ("zero", "mean", "gaussian")


@pytest.mark.parametrize(
    ("kwargs", "pattern"),
    [
        ({"strategy": "ones"}, r"intervention.strategy='ones' is unknown"),
        (
            {"image_space": "latent"},
            r"intervention.image_space='latent' is unknown; allowed values: "
            r"\('raw', 'centered', 'normalized'\)",
        ),
        ({"image_space": "centered"}, r"image_space='centered' is not a space for images"),
        ({"state_space": "x"}, r"intervention.state_space='x' is unknown"),
        ({"noise_scale": -1.0}, r"noise_scale=-1.0 must be >= 0"),
    ],
)
def test_bad_intervention_config(kwargs, pattern) -> None:
    with pytest.raises(ValueError, match=pattern):
        InterventionConfig(**kwargs)


@pytest.mark.parametrize("lib", ["numpy", "torch"])
def test_about_a_center_zero_is_the_center_and_noise_keeps_its_size(lib) -> None:
    """``centered`` do(S): ``zero`` gives the center (the dataset mean) exactly, in the
    state's dtype; ``gaussian`` adds noise scaled by the offsets' std; ``mean`` is the mean
    of the offsets, shifted back."""
    rng = np.random.default_rng(3)
    x = rng.normal(size=(2, 5)).astype(np.float32)
    center = rng.normal(size=5).astype(np.float32)
    xx = torch.from_numpy(x) if lib == "torch" else x
    zero = intervene_about(xx, center, "zero")
    assert zero.dtype == xx.dtype and tuple(zero.shape) == (2, 5)
    assert np.array_equal(np.asarray(zero), np.broadcast_to(center, (2, 5)))
    noisy = np.asarray(intervene_about(xx, center, "gaussian", seed=4))
    offsets = xx - (torch.from_numpy(center) if lib == "torch" else center)
    draw = np.asarray(intervene(offsets, "gaussian", seed=4)) - np.asarray(offsets)
    np.testing.assert_allclose(noisy - x, draw, atol=1e-5)  # the offsets' draw, around x
    np.testing.assert_allclose(
        np.asarray(intervene_about(xx, center, "mean")),
        center + (x - center).mean(axis=1, keepdims=True),
        atol=1e-6,
    )
    assert np.array_equal(np.asarray(intervene_about(xx, None, "zero")), np.zeros((2, 5)))
    with pytest.raises(ValueError, match="state center has \\(4,\\) values"):
        intervene_about(xx, center[:4], "zero")


def test_centered_is_the_default_space_of_do_s() -> None:
    assert InterventionConfig().state_space == "centered"
    assert InterventionConfig().image_space == "raw"
