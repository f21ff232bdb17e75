"""Perturbations: parsing and refusals, the sensor kinds, and the tabletop's scene kinds
(``none`` after a perturbed episode is the unperturbed episode to the bit)."""

from __future__ import annotations

import numpy as np
import pytest

from workers.envs.wrappers.image_ops import PerturbedImages, perturb_image
from workers.envs.wrappers.perturbation_grammar import KINDS, Perturbation, parse, split_task


def test_parse_spellings_and_refusals() -> None:
    assert parse("none") is None and parse(None) is None
    assert parse("camera_shift:0.12") == Perturbation("camera_shift", 0.12)
    assert parse({"kind": "light_dim", "severity": 0.4}) == Perturbation("light_dim", 0.4)
    with pytest.raises(ValueError, match=r"kind .fog. is unknown; .*camera_shift"):
        parse("fog:0.3")
    with pytest.raises(ValueError, match=r"out of range, 0 < severity <= 0.3 \(m"):
        parse("camera_shift:0.5")
    with pytest.raises(ValueError, match="severity must be a number"):
        parse("image_noise:lots")
    with pytest.raises(ValueError, match="KIND:SEVERITY"):
        parse("camera_shift")
    assert split_task("pick_color@image_blur:2") == ("pick_color", Perturbation("image_blur", 2.0))
    assert split_task("pick_color") == ("pick_color", None)


def test_sensor_kinds_are_seeded_and_do_what_they_say() -> None:
    rng = np.random.default_rng(0)
    image = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8)
    noise = Perturbation("image_noise", 0.1)
    a = perturb_image(image, noise, noise.rng(0, "t", 1, 5))
    b = perturb_image(image, noise, noise.rng(0, "t", 1, 5))
    c = perturb_image(image, noise, noise.rng(0, "t", 1, 6))  # the next step: fresh noise
    assert a.dtype == np.uint8 and a.shape == image.shape
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert np.std(a.astype(float) - image) == pytest.approx(25.5, rel=0.15)  # clipped a bit
    blurred = perturb_image(image, Perturbation("image_blur", 2.0), rng)
    assert (
        np.abs(np.diff(blurred.astype(float), axis=0)).mean()
        < 0.5 * np.abs(np.diff(image.astype(float), axis=0)).mean()
    )
    assert not perturb_image(image, Perturbation("image_blackout", 1.0), rng).any()  # black
    half = perturb_image(image, Perturbation("image_blackout", 0.5), rng)
    assert np.abs(half.astype(float) - image / 2).max() <= 0.5
    seen = []

    def rng_for(camera: str) -> np.random.Generator:
        seen.append(camera)
        return noise.rng(0, "t", 0, 0)

    lazy = PerturbedImages({"a": image, "b": image}, noise, rng_for)
    assert lazy["a"] is lazy["a"] and seen == ["a"]  # drawn once, when read
    assert set(lazy) == {"a", "b"}


@pytest.mark.sim
@pytest.mark.slow
def test_tabletop_scene_kinds_and_bit_identical_none() -> None:
    from workers.rendering import configure_rendering

    configure_rendering()
    from workers.envs.suites.tabletop.env import TabletopEnv
    from workers.envs.wrappers.perturbations import PerturbedEnv

    def episode(env, task_id: str, n: int = 3) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        obs = env.reset(task_id, 2, 0)
        out = [(obs.images["agentview"].copy(), obs.images["wrist"].copy(), obs.state.copy())]
        for _ in range(n):
            obs = env.step(np.array([0.3, 0.0, -0.2, 0, 0, 0, -1.0]))
            out.append((obs.images["agentview"].copy(), obs.images["wrist"].copy(), obs.state))
        return out

    fresh = TabletopEnv(image_size=48)
    plain = episode(fresh, "pick_color")
    fresh.close()
    # table_color at 0.02 moves no pixel of the bright, textured table: 0.3 does
    severity = {"distractors": 1, "table_color": 0.3}
    cases = [f"{k}:{severity.get(k, 0.02)}" for k, v in KINDS.items() if v.scene]
    env = PerturbedEnv(TabletopEnv(image_size=48), [None, *[parse(c) for c in cases]])
    assert {t.task_id for t in env.tasks()} >= {f"pick_color@{c}" for c in cases}
    for case in cases:
        kind = case.split(":")[0]
        perturbed = episode(env, f"pick_color@{case}")
        view, _, state = perturbed[0]
        if kind in ("init_jitter", "distractors"):  # the layout changed, the robot's start not
            assert np.array_equal(state, plain[0][2]) and not np.array_equal(view, plain[0][0])
        else:  # camera, light, table: pixels only; the physics is untouched
            assert all(np.array_equal(p[2], q[2]) for p, q in zip(perturbed, plain, strict=True))
            assert not np.array_equal(view, plain[0][0]), kind
        again = episode(env, f"pick_color@{case}")  # seeded: the same twice
        assert all(
            np.array_equal(x, y)
            for p, q in zip(again, perturbed, strict=True)
            for x, y in zip(p, q, strict=True)
        )
        # none right after: the unperturbed episode to the bit
        after = episode(env, "pick_color")
        assert all(
            np.array_equal(x, y)
            for p, q in zip(after, plain, strict=True)
            for x, y in zip(p, q, strict=True)
        ), kind
    dim = episode(env, "pick_color@light_dim:0.5", 0)[0][0]
    assert dim.mean() < 0.8 * plain[0][0].mean()
    env.close()
