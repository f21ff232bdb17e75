"""Object-hidden renders of the tabletop (Policy Contrastive Decoding's object-removed image):
the objects the instruction names, and only they, leave the image; the simulation is untouched.

Where the objects are comes from MuJoCo's segmentation rendering on the same model and camera,
with sites left out: robosuite's gripper draws a translucent site (``grip_site_cylinder``) that
the colour image shows the cube through, while a segmentation gives the pixel to the site."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

pytestmark = [pytest.mark.sim, pytest.mark.slow]

TASKS = ("pick_color", "stack_color", "organize")
SIZE = 64
# a few steps that move the arm over the table and close the gripper (the wrist camera moves)
ACTIONS = [np.array([0.4, 0.2, -0.3, 0.0, 0.0, 0.1, -1.0])] * 4 + [
    np.array([-0.2, 0.3, -0.2, 0.1, 0.0, 0.0, 1.0])
] * 4


@pytest.fixture(scope="module")
def env() -> Iterator[Any]:
    from workers.rendering import configure_rendering

    configure_rendering()
    from workers.envs.suites.tabletop.env import TabletopEnv

    e = TabletopEnv(image_size=SIZE, cameras=("agentview", "wrist"))
    yield e
    e.close()


class Segmenter:
    """Geom ids per pixel (-1: no geom) from a segmentation render of the env's current scene,
    through the same camera at the same size as its images, sites left out."""

    def __init__(self, env: Any) -> None:
        import mujoco

        self.env = env
        self.renderers: dict[str, Any] = {}
        self.option = mujoco.MjvOption()
        self.option.sitegroup[:] = 0

    def __call__(self, camera: str) -> np.ndarray:
        import mujoco

        from workers.envs.suites.tabletop.env import CAMERAS

        key = self.env._ep.scene_key
        scene = self.env._scenes[key]
        if key not in self.renderers:
            r = mujoco.Renderer(scene.sim.model._model, SIZE, SIZE)
            r.enable_segmentation_rendering()
            self.renderers[key] = r
        r = self.renderers[key]
        r.update_scene(scene.sim.data._data, camera=CAMERAS[camera], scene_option=self.option)
        seg = r.render()
        return np.where(seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM), seg[..., 0], -1)

    def close(self) -> None:
        for r in self.renderers.values():
            r.close()


@pytest.fixture(scope="module")
def segment(env: Any) -> Iterator[Segmenter]:
    s = Segmenter(env)
    yield s
    s.close()


def _geom_names(env: Any, ids: tuple[int, ...]) -> set[str]:
    import mujoco

    model = env._scenes[env._ep.scene_key].sim.model._model
    return {mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, g) for g in ids}


def _check_hidden_where_the_objects_are(env: Any, obs: Any, segment: Segmenter) -> int:
    """Hidden vs observed images of the current state: equal to the bit away from the objects'
    pixels (one pixel of margin), different in nearly every one of them, and no object geom
    left in a segmentation with them hidden; the number of object pixels seen."""
    from scipy.ndimage import binary_dilation

    from workers.envs.mujoco.scene_edits import geoms_hidden

    ids = env.hidden_object_geoms()
    hidden = env.object_hidden_images()
    assert set(hidden) == set(env.cameras)
    seen = 0
    for cam in env.cameras:
        shown, gone = obs.images[cam], hidden[cam]
        assert gone.dtype == shown.dtype == np.uint8 and gone.shape == shown.shape
        seg = segment(cam)
        mask = np.isin(seg, ids)
        near = binary_dilation(mask, iterations=1)
        diff = np.abs(gone.astype(int) - shown.astype(int)).max(axis=-1)
        assert (diff[~near] == 0).all(), f"{cam}: {int((diff[~near] > 0).sum())} px changed away"
        if mask.any():
            changed = diff[mask] > 40
            assert changed.mean() > 0.95, f"{cam}: only {changed.mean():.0%} of object px changed"
        seen += int(mask.sum())
        with geoms_hidden(env._scenes[env._ep.scene_key].sim.model._model, ids):
            seg_hidden = segment(cam)
        assert not np.isin(seg_hidden, ids).any(), f"{cam}: an object geom is still rendered"
        # what the objects covered shows; every other pixel keeps its geom
        assert np.array_equal(seg_hidden[~mask], seg[~mask])
    return seen


@pytest.mark.parametrize("task", TASKS)
def test_the_hidden_render_differs_only_where_the_objects_are(env, segment, task) -> None:
    for episode in (0, 1):
        obs = env.reset(task, episode, 0)
        assert _check_hidden_where_the_objects_are(env, obs, segment) > 0  # they are in view
        for action in ACTIONS:
            obs = env.step(action)
        _check_hidden_where_the_objects_are(env, obs, segment)


@pytest.mark.parametrize("task", TASKS)
def test_the_instructions_objects_are_hidden_and_the_others_kept(env, task) -> None:
    """pick_color: the named cube; stack_color: the two named cubes; organize: the five cubes
    and the bin. The unnamed cube of pick_color and stack_color stays in the image."""
    obs = env.reset(task, 3, 0)
    ep = env._ep
    names = _geom_names(env, env.hidden_object_geoms())
    named = {ep.colors[i] for i in ep.targets}
    assert all(color in obs.status.instruction for color in named)
    want = {f"cube_{c}_g0" for c in named} | {f"cube_{c}_g0_vis" for c in named}
    if task == "organize":
        assert named == set(ep.colors)
        walls = ("floor", "wall_n", "wall_s", "wall_e", "wall_w")
        want |= {f"bin_{p}_g0{v}" for p in walls for v in ("", "_vis")}
    assert names == want
    assert len(named) == {"pick_color": 1, "stack_color": 2, "organize": 5}[task]


@pytest.mark.parametrize("task", TASKS)
def test_the_call_leaves_the_simulation_and_later_observations_bit_identical(env, task) -> None:
    """One episode with object-hidden renders at every step (before and after the observation's
    own images are read), one without: the same simulator states and observations to the bit,
    and the model's colours restored."""
    import mujoco

    def run(with_hidden: bool) -> list[tuple[np.ndarray, ...]]:
        obs = env.reset(task, 5, 1)
        scene = env._scenes[env._ep.scene_key]
        model, data = scene.sim.model._model, scene.sim.data._data
        rgba = model.geom_rgba.copy()
        spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
        state = np.empty(mujoco.mj_stateSize(model, spec))
        out = []
        for k in range(len(ACTIONS) + 1):
            if with_hidden and k % 2 == 0:
                env.object_hidden_images()
            images = [obs.images[c].copy() for c in env.cameras]
            if with_hidden:
                mujoco.mj_getState(model, data, state, spec)
                before = state.copy()
                env.object_hidden_images()
                mujoco.mj_getState(model, data, state, spec)
                assert np.array_equal(state, before)
                assert np.array_equal(model.geom_rgba, rgba)
            mujoco.mj_getState(model, data, state, spec)
            priv = obs.privileged
            sim = (state.copy(), data.qacc_warmstart.copy(), np.asarray(priv["cube_pos"]))
            out.append((*images, obs.state.copy(), *sim, np.asarray(priv["grasped"])))
            if k < len(ACTIONS):
                obs = env.step(ACTIONS[k])
        return out

    plain, called = run(False), run(True)
    assert len(plain) == len(called)
    for k, (a, b) in enumerate(zip(plain, called, strict=True)):
        for x, y in zip(a, b, strict=True):
            assert x.dtype == y.dtype and np.array_equal(x, y), f"step {k} differs"


def test_the_suite_says_it_renders_hidden_objects_and_refuses_before_a_reset() -> None:
    from tests.doubles.envs import NoHiddenRenderMarkerEnv
    from workers.envs.base import suite_info
    from workers.envs.suites.tabletop.env import TabletopEnv
    from workers.envs.wrappers.perturbations import PerturbedEnv

    assert suite_info(TabletopEnv).renders_hidden_objects is True
    assert suite_info(NoHiddenRenderMarkerEnv).renders_hidden_objects is False
    plain = PerturbedEnv(NoHiddenRenderMarkerEnv(), [None])
    assert suite_info(plain).renders_hidden_objects is False
    with pytest.raises(NotImplementedError, match="renders_hidden_objects"):
        plain.object_hidden_images()
    with pytest.raises(RuntimeError, match="before reset"):
        TabletopEnv(image_size=SIZE).object_hidden_images()


@pytest.mark.parametrize("case", ["image_noise:0.1", "camera_shift:0.05", "distractors:2"])
def test_a_perturbed_episode_hides_the_same_objects_under_the_same_perturbation(
    env, segment, case
) -> None:
    """Through the perturbation wrapper: image noise is drawn as for the observation (so the
    images differ only at the objects), a scene kind is in both renders, and the distractors
    of the ``distractors`` kind stay."""
    from workers.envs.base import suite_info
    from workers.envs.wrappers.perturbation_grammar import parse
    from workers.envs.wrappers.perturbations import PerturbedEnv

    wrapped = PerturbedEnv(env, [None, parse(case)])
    try:
        assert suite_info(wrapped).renders_hidden_objects is True
        for task in ("pick_color", "organize"):
            plain_view = wrapped.reset(task, 4, 0).images["agentview"]
            plain_hidden = wrapped.object_hidden_images()
            obs = wrapped.reset(f"{task}@{case}", 4, 0)
            assert obs.status.task_id == f"{task}@{case}"
            for action in ACTIONS[:3]:
                obs = wrapped.step(action)
            _check_hidden_where_the_objects_are(wrapped, obs, segment)
            if case.startswith("distractors"):  # still seen with the objects hidden
                import mujoco

                from workers.envs.mujoco.scene_edits import geoms_hidden

                model = env._scenes[env._ep.scene_key].sim.model._model
                grey = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "distractor_0_g0_vis")
                assert grey not in env.hidden_object_geoms()
                with geoms_hidden(model, env.hidden_object_geoms()):
                    assert (segment("agentview") == grey).any()
            obs = wrapped.reset(f"{task}@{case}", 4, 0)
            hidden = wrapped.object_hidden_images()
            # the perturbation is in the hidden render: it is not the unperturbed one
            assert not np.array_equal(hidden["agentview"], plain_hidden["agentview"])
            assert not np.array_equal(obs.images["agentview"], plain_view)
    finally:  # the module's env: the next test's resets unperturbed
        env.set_perturbation(None)


def test_an_env_server_forwards_the_hidden_render_bit_for_bit(env) -> None:
    """The tabletop in an env server renders the same object-hidden images as in-process; an
    env without them is refused there with the flag named."""
    import sys

    from workers.envs.base import suite_info
    from workers.envs.server.client import EnvServerClient, ServerSpec

    spec = ServerSpec(python=sys.executable, timeout_s=120)
    remote = EnvServerClient(
        "workers.envs.suites.tabletop.env:TabletopEnv", {"image_size": SIZE}, spec
    )
    try:
        assert suite_info(remote).renders_hidden_objects is True
        here, there = env.reset("stack_color", 2, 0), remote.reset("stack_color", 2, 0)
        for action in ACTIONS[:2]:
            here, there = env.step(action), remote.step(action)
        mine, theirs = env.object_hidden_images(), remote.object_hidden_images()
        assert set(theirs) == set(mine)
        for cam in mine:
            assert theirs[cam].dtype == mine[cam].dtype
            assert np.array_equal(theirs[cam], mine[cam])
            assert np.array_equal(there.images[cam], here.images[cam])
    finally:
        remote.close()
    fake = EnvServerClient("tests.doubles.envs:NoHiddenRenderMarkerEnv", {}, spec)
    try:
        assert suite_info(fake).renders_hidden_objects is False
        fake.reset("reach", 0, 0)
        with pytest.raises(NotImplementedError, match="renders_hidden_objects"):
            fake.object_hidden_images()
    finally:
        fake.close()
