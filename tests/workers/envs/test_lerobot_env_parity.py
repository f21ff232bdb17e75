"""Parity with lerobot-eval on lerobot's own env types (``env.suite: lerobot``): the same
checkpoint and seed give lerobot-eval's episodes, the same action sent at every step, bit for
bit, and the same success and length.

The reference is lerobot's code path itself: its env config, ``make_env``, ``make_policy``, its
processors and ``eval_policy_all``. Ours: the run's pre-flight (``plan_run``) and episode
worker on the ``lerobot`` suite. On PushT (pymunk, 96 px) and ALOHA (480x640) the checkpoint is
ACT built offline with the env's keys (``observation.image``, ``observation.state``, the
action), random weights, replanning every ``n_action_steps`` = 5; on MetaWorld (MuJoCo, 480 px,
``button-press-v3``) a learned one, the zoo's tiny VLA trained at 96 px and resizing lerobot's
480 px frames to it (``resize_images_to``).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.support.lerobot_eval import lerobot_eval_env
from training.toy_checkpoints import build_act

STEPS = 50
#: ALOHA renders 480x640 and its ACT reads that image: 20 steps (4 inferences) an episode keep
#: the comparison bit for bit at two fifths of the cost
ALOHA_STEPS = 20
#: MetaWorld renders 480 px frames (OSMesa) for both sides: 30 steps (8 inferences) an episode
METAWORLD_STEPS = 30
EPISODES = 2
SEED = 5


def _needs(module: str, package: str) -> pytest.MarkDecorator:
    return pytest.mark.skipif(
        importlib.util.find_spec(module) is None,
        reason=f"{package} is not installed (make setup installs it)",
    )


def _act(tmp_path: Path, image: int | tuple[int, int], dims: int, cam: str) -> Path:
    """ACT with the env's keys (``dims``-d state and action), random weights, a chunk of 10
    of which it executes ``n_action_steps`` = 5 per inference."""
    return build_act(
        tmp_path / "act", image=image, state=dims, action=dims, cams=(cam,), chunk=10,
        n_action_steps=5,
    )  # fmt: skip


def _our_episodes(
    ckpt: Path,
    tmp_path: Path,
    env_params: dict[str, Any],
    replan: int = 5,
    cell: dict[str, Any] | None = None,
    episodes: int = EPISODES,
    steps: list | None = None,
) -> tuple[list[list[np.ndarray]], list]:
    """idr-eval's episodes of ``ckpt``; ``cell``: the one cell's IDR settings and
    intervention (default: the baseline); ``steps``: where given, each episode's step rows
    (one per inference, its diagnostics) are appended to it."""
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import config_from_dict
    from workers.episode.worker import EpisodeWorker

    cfg = config_from_dict(
        {
            "name": "lerobot_parity",
            "backbone": {"kind": "lerobot", "params": {"path": str(ckpt)}},
            "env": {"suite": "lerobot", "params": env_params},
            "episodes_per_task": episodes,
            "seed": SEED,
            "grid": [{"mode": [(cell or {}).get("mode", "baseline")]}],
            "idr": {k: v for k, v in (cell or {}).items() if k not in ("mode", "intervention")},
            "intervention": (cell or {}).get("intervention", {}),
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
        }
    )
    plan = plan_run(cfg, tmp_path / "run")
    assert plan.worker_spec.replan_steps == replan  # the checkpoint's n_action_steps
    worker = EpisodeWorker(plan.worker_spec)
    actions: list[list[np.ndarray]] = []
    env = worker.env
    step = env.step

    def recording_step(action):
        actions[-1].append(np.asarray(action, dtype=np.float32).copy())
        return step(action)

    env.step = recording_step
    rows = []
    try:
        for spec in plan.specs:
            actions.append([])
            result = worker.run_episode(spec)
            assert result.episode.error is None, result.episode.error
            rows.append(result.episode)
            if steps is not None:
                steps.append(result.steps)
    finally:
        worker.close()
    return actions, rows


def _assert_same_episodes(theirs, info, ours, rows, moves: float = 0.1) -> None:
    """``moves``: how far some action dimension must range over episode 0 (random ACT weights
    move the normalized actions less on some envs)."""
    assert len(theirs) == len(ours) == len(rows)
    for e, (a, b, row) in enumerate(zip(theirs, ours, rows, strict=True)):
        assert len(a["actions"]) == len(b) == row.steps, f"episode {e}: lengths"
        for t, (x, y) in enumerate(zip(a["actions"], b, strict=True)):
            assert np.array_equal(x.astype(np.float32), y), f"episode {e} step {t}: {x} vs {y}"
        assert bool(info["per_task"][0]["metrics"]["successes"][e]) == row.success
    # the two episodes start apart (seed + e) and the actions follow the observation
    assert len(ours) < 2 or not np.array_equal(ours[0][0], ours[1][0])
    assert np.ptp(np.stack(ours[0]), axis=0).max() > moves  # not one constant action


@pytest.mark.slow
@_needs("gym_pusht", "gym-pusht")
def test_the_lerobot_suite_gives_lerobot_evals_pusht_episodes(tmp_path) -> None:
    from lerobot.envs.configs import PushtEnv

    size = 96
    ckpt = _act(tmp_path, size, 2, "image!")
    env = {"observation_height": size, "observation_width": size, "episode_length": STEPS}
    ours, rows = _our_episodes(ckpt, tmp_path, {"type": "pusht", **env})
    theirs, info = lerobot_eval_env(PushtEnv(**env), ckpt, episodes=EPISODES, seed=SEED)
    _assert_same_episodes(theirs, info, ours, rows)


@pytest.mark.slow
@pytest.mark.sim
@_needs("gym_aloha", "gym-aloha")
def test_the_lerobot_suite_gives_lerobot_evals_aloha_episodes(tmp_path) -> None:
    """ALOHA (dm_control, 14-d bimanual actions, one 480x640 camera ``top``): the checkpoint
    declares observation.images.top (3, 480, 640), and both sides run the config's
    episode_length."""
    from lerobot.envs.configs import AlohaEnv

    from workers.rendering import configure_rendering

    configure_rendering()
    ckpt = _act(tmp_path, (480, 640), 14, "top")
    env = {"task": "AlohaInsertion-v0", "episode_length": ALOHA_STEPS}
    ours, rows = _our_episodes(ckpt, tmp_path, {"type": "aloha", **env})
    theirs, info = lerobot_eval_env(AlohaEnv(**env), ckpt, episodes=EPISODES, seed=SEED)
    _assert_same_episodes(theirs, info, ours, rows, moves=0.02)  # it ranges over 0.06 here


@pytest.mark.slow
@pytest.mark.sim
@_needs("metaworld", "metaworld")
def test_a_zoo_checkpoint_trained_at_96px_gives_lerobot_evals_metaworld_episodes(tmp_path) -> None:
    """A learned checkpoint, not random weights: the zoo's tiny VLA (trained by lerobot-train on
    the zoo's MetaWorld demonstrations at 96 px; ``resize_images_to: 96`` in its config) reads
    lerobot's 480 px frames, resized inside the policy, and lerobot's task description. The
    pre-flight lets the size through because the policy resizes.

    MetaWorld's episode budget is its env's 500 steps, not the config's episode_length: both
    sides are cut to METAWORLD_STEPS here (ours by env.params.max_steps, lerobot-eval's rollout
    by the budget it reads). Both sides' MuJoCo GL objects are freed under their own contexts
    (workers.rendering.release_gl_context): one left to the collector can delete the other
    side's framebuffer mid-episode (black frames from then on)."""
    from lerobot.envs.configs import MetaworldEnv

    from training.zoo import ROOT
    from workers.rendering import configure_rendering

    configure_rendering()
    ckpt = ROOT / "checkpoints" / "zoo" / "metaworld" / "tiny_vla"
    task = "button-press-v3"
    env = {"type": "metaworld", "task": task, "max_steps": METAWORLD_STEPS}
    ours, rows = _our_episodes(ckpt, tmp_path, env, replan=4)
    theirs, info = lerobot_eval_env(
        MetaworldEnv(task=task), ckpt, episodes=EPISODES, seed=SEED, max_steps=METAWORLD_STEPS
    )
    _assert_same_episodes(theirs, info, ours, rows)


@pytest.mark.slow
@_needs("gym_pusht", "gym-pusht")
def test_a_history_fed_baseline_follows_lerobot_evals_own_rollout_on_pusht(tmp_path) -> None:
    """VQ-BeT reads the observation queues its select_action fills at every step (2 frames):
    idr-eval's baseline sends the episode's past frames with each request and lends the base
    queues built from them, so its actions follow lerobot-eval's rollout of the bare
    checkpoint (codes sampled near temperature 0: the argmax)."""
    from lerobot.envs.configs import PushtEnv

    from training.toy_checkpoints import build_vqbet

    size = 96
    ckpt = build_vqbet(
        tmp_path / "vqbet", image=size, state=2, action=2, temperature=1e-6, cams=("image!",)
    )
    env = {"observation_height": size, "observation_width": size, "episode_length": STEPS}
    ours, rows = _our_episodes(ckpt, tmp_path, {"type": "pusht", **env}, replan=4)
    theirs, _info = lerobot_eval_env(PushtEnv(**env), ckpt, episodes=EPISODES, seed=SEED)
    assert len(theirs) == len(ours) == EPISODES
    for e, (a, b, row) in enumerate(zip(theirs, ours, rows, strict=True)):
        assert len(a["actions"]) == len(b) == row.steps == STEPS, f"episode {e}: lengths"
        worst = max(
            float(np.abs(x.astype(np.float32) - y).max())
            for x, y in zip(a["actions"], b, strict=True)
        )
        assert worst <= 1e-5, f"episode {e}: actions differ by {worst}"
    assert np.ptp(np.stack(ours[0]), axis=0).max() > 0.1  # the actions move


@pytest.mark.slow
@_needs("gym_pusht", "gym-pusht")
@pytest.mark.parametrize("mode", ["E", "random"])
def test_idr_in_lerobot_eval_is_the_harness_cell_step_for_step(tmp_path, mode) -> None:
    """The idr policy as lerobot-eval runs it (an IDR folder around ACT) and idr-eval's cell of
    the same mode, closed loop on PushT over 2 episodes of 50 steps, each side on its default
    runtime settings (executed horizon: the base's n_action_steps under lerobot's protocol;
    refined actions clipped into the dataset's bounds; do(S) about the dataset mean): the same
    action at every step. A push large enough that the clipping acts (alpha 2, and the same
    cell unclipped differs). A placebo's direction comes from the harness's step seed;
    lerobot-eval's run is given the same seeds."""
    from lerobot.envs.configs import PushtEnv

    from tests.lerobot_policy_idr.conftest import make_idr

    size = 96
    ckpt = _act(tmp_path, size, 2, "image!")
    folder = make_idr(ckpt, tmp_path / "idr", "--mode", mode, "--tau", "1e9", "--alpha", "2")
    env = {"observation_height": size, "observation_width": size, "episode_length": STEPS}
    cell = {"mode": mode, "tau": 1e9, "alpha": 2.0}
    ours, rows = _our_episodes(ckpt, tmp_path, {"type": "pusht", **env}, cell=cell)
    seeds = _harness_seeds(rows, replan=5)
    theirs, info = _lerobot_eval_with_seeds(PushtEnv(**env), folder, seeds)
    _assert_same_episodes(theirs, info, ours, rows)
    base, _ = _our_episodes(ckpt, tmp_path / "base", {"type": "pusht", **env})
    assert not np.array_equal(np.stack(base[0]), np.stack(ours[0]))  # the mode refined
    unclipped = {**cell, "clip_actions": False}
    loose, _ = _our_episodes(ckpt, tmp_path / "loose", {"type": "pusht", **env}, cell=unclipped)
    assert not np.array_equal(np.stack(loose[0]), np.stack(ours[0]))  # the clipping acted


@pytest.mark.slow
@_needs("gym_pusht", "gym-pusht")
def test_a_history_fed_sampling_base_under_idr_is_the_harness_cell_in_lerobot_eval(
    tmp_path,
) -> None:
    """Diffusion (DDIM, two observation steps): shared noise and the observation history,
    closed loop on PushT in lerobot-eval through the idr policy and in idr-eval's cell (mode
    E): the same action at every step, lerobot-eval fed the harness's noise draws."""
    from lerobot.envs.configs import PushtEnv

    from tests.lerobot_policy_idr.conftest import make_idr
    from training.toy_checkpoints import build_diffusion

    size = 96
    ckpt = build_diffusion(
        tmp_path / "diffusion", image=size, state=2, action=2, n_obs_steps=2, cams=("image!",)
    )
    folder = make_idr(ckpt, tmp_path / "idr", "--mode", "E", "--tau", "1e9")
    env = {"observation_height": size, "observation_width": size, "episode_length": STEPS}
    cell = {"mode": "E", "tau": 1e9}  # both sides on their defaults (do(S) centered, clipped)
    ours, rows = _our_episodes(ckpt, tmp_path, {"type": "pusht", **env}, replan=4, cell=cell)
    seeds = _harness_seeds(rows, replan=4)
    theirs, info = _lerobot_eval_with_seeds(PushtEnv(**env), folder, seeds)
    _assert_same_episodes(theirs, info, ours, rows, moves=0.01)


def _harness_seeds(rows: list, replan: int) -> list[int]:
    """The step seeds idr-eval gave each inference of the episodes in ``rows``, in order."""
    from workers.episode.worker import step_seed

    return [
        step_seed(row.seed, row.task_id, row.episode_index, k)
        for row in rows
        for k in range(-(-row.steps // replan))
    ]


def _lerobot_eval_with_seeds(
    env_cfg: Any, folder: Path, seeds: list[int], episodes: int = EPISODES, **kw: Any
):
    """lerobot-eval's rollout of the IDR folder, idr-eval's step seeds fed to its inferences in
    order: the policy draws the base's noise (an ensemble's draws), a placebo's direction, from
    each as idr-eval does; lerobot-eval itself would draw them from torch's RNG. ``kw``: to
    ``lerobot_eval_env``."""
    from lerobot_policy_idr.modeling_idr import IDRPolicy

    feed = iter(seeds)
    infer = IDRPolicy._infer

    def seeded(self, batch, noise=None, seed=None):
        return infer(self, batch, noise, next(feed) if seed is None else seed)

    IDRPolicy._infer = seeded
    try:
        return lerobot_eval_env(env_cfg, folder, episodes=episodes, seed=SEED, **kw)
    finally:
        IDRPolicy._infer = infer
