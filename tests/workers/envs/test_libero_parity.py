"""Parity with lerobot-eval: under ``protocol: lerobot`` the same checkpoint and seed give
lerobot's own episodes: the same actions sent to the simulator, bit for bit, the same simulator
states after every step, the same success and length per episode.

The reference is lerobot's code path itself, not a copy: its LIBERO env config and ``make_env``,
``make_policy``, its policy and env processors and ``eval_policy_all`` (what ``lerobot-eval``
runs), on an ACT checkpoint built offline with lerobot's LIBERO camera keys (``image``,
``image2``), random weights, 2 episodes of 40 steps, replanning every ``n_action_steps`` = 5.
Ours: the run's own pre-flight (``plan_run``: camera keys, render size and replan rule from the
checkpoint's config.json) and episode worker.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.support.lerobot_eval import lerobot_eval_libero, sim_state
from training.toy_checkpoints import build_act

SIZE = 64  # the checkpoint declares 64 px; our pre-flight renders at it, lerobot is told it
STEPS = 25  # five chunks of n_action_steps = 5, two episodes, both sides
EPISODES = 2
SEED = 7
TASK = "libero_spatial/0"


def _lerobot_episodes(ckpt: Path) -> tuple[list[dict], dict]:
    return lerobot_eval_libero(
        ckpt, steps=STEPS, episodes=EPISODES, seed=SEED, size=SIZE, states=True
    )


def _our_episodes(ckpt: Path, tmp_path: Path) -> tuple[list[dict], list, dict]:
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import config_from_dict
    from workers.episode.worker import EpisodeWorker

    cfg = config_from_dict(
        {
            "name": "parity",
            "backbone": {"kind": "lerobot", "params": {"path": str(ckpt)}},
            "env": {
                "suite": "libero",
                "tasks": [TASK],
                "params": {
                    "protocol": "lerobot",
                    "suites": ["libero_spatial"],
                    "max_steps": {"libero_spatial": STEPS},
                },
            },
            "episodes_per_task": EPISODES,
            "seed": SEED,
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
            "output_root": str(tmp_path),
        }
    )
    plan = plan_run(cfg, tmp_path / "run")
    worker = EpisodeWorker(plan.worker_spec)
    episodes: list[dict] = []
    env = worker.env
    step = env.step

    def recording_step(action):
        obs = step(action)
        episodes[-1]["actions"].append(np.asarray(action, dtype=np.float32).copy())
        episodes[-1]["states"].append(sim_state(env._sim.sim))
        return obs

    env.step = recording_step
    rows = []
    try:
        for spec in plan.specs:
            episodes.append({"actions": [], "states": []})
            result = worker.run_episode(spec)
            assert result.episode.error is None, result.episode.error
            rows.append(result.episode)
    finally:
        worker.close()
    return episodes, rows, {"fit": plan.fit, "worker_spec": plan.worker_spec}


@pytest.mark.slow
def test_lerobot_protocol_gives_lerobot_evals_episodes(tmp_path) -> None:
    ckpt = build_act(
        tmp_path / "act", image=SIZE, cams=("image", "image2"), chunk=10, n_action_steps=5
    )
    ours, rows, plan = _our_episodes(ckpt, tmp_path)
    # the pre-flight read the checkpoint: lerobot's LIBERO names, its size, its n_action_steps
    assert plan["fit"].camera_map == {"agentview": "image", "wrist": "image2"}
    assert plan["worker_spec"].env_params["image_size"] == SIZE
    assert plan["worker_spec"].replan_steps == 5
    theirs, info = _lerobot_episodes(ckpt)

    assert len(theirs) == len(ours) == EPISODES
    for e, (a, b, row) in enumerate(zip(theirs, ours, rows, strict=True)):
        assert len(a["actions"]) == len(b["actions"]) == row.steps, f"episode {e}: lengths"
        for t, (x, y) in enumerate(zip(a["actions"], b["actions"], strict=True)):
            assert x.dtype == y.dtype == np.float32
            assert np.array_equal(x, y), f"episode {e} step {t}: actions {x} vs {y}"
        for t, (x, y) in enumerate(zip(a["states"], b["states"], strict=True)):
            assert np.array_equal(x, y), f"episode {e} step {t}: simulator states differ"
        per_episode = info["per_task"][0]["metrics"]
        assert bool(per_episode["successes"][e]) == row.success
    # the two episodes differ (seed + e, init state e): parity is not two copies of one
    assert not np.array_equal(ours[0]["states"][0], ours[1]["states"][0])
    # the policy moved the arm: the comparison is about actions that matter
    assert np.abs(np.stack(ours[0]["actions"])[:, :6]).max() > 1e-3


@pytest.mark.slow
def test_float32_state_arithmetic_is_lerobots(tmp_path) -> None:
    """Our float32 axis-angle equals lerobot's LiberoProcessorStep's, bit for bit."""
    import torch
    from lerobot.processor.env_processor import LiberoProcessorStep

    from workers.envs.suites.libero.protocol import quat_to_axis_angle_f32

    rng = np.random.default_rng(0)
    quats = rng.normal(size=(500, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats = np.concatenate([quats, [[0, 0, 0, 1.0], [0, 0, 1.0, 0]]])
    step = LiberoProcessorStep()
    for q in quats:
        theirs = step._quat2axisangle(torch.from_numpy(q[None]))[0].numpy()
        assert np.array_equal(quat_to_axis_angle_f32(q), theirs), q
