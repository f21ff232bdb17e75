"""Parity with lerobot-eval on lerobot's own env types (``env.suite: lerobot``): the same
checkpoint and seed give lerobot-eval's episodes, the same action sent at every step, bit for
bit, and the same success and length.

The reference is lerobot's code path itself: its PushT env config, ``make_env``, ``make_policy``,
its processors and ``eval_policy_all``. The checkpoint: ACT built offline with PushT's keys
(``observation.image`` at 96 px, a 2-d ``observation.state``, 2-d actions), random weights,
replanning every ``n_action_steps`` = 5. Ours: the run's pre-flight (``plan_run``) and episode
worker on the ``lerobot`` suite.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tests.support.lerobot_eval import lerobot_eval_env
from tests.workers.backbones.lerobot_fixtures import build_act

pytest.importorskip("gym_pusht", reason="gym-pusht is not installed (make setup installs it)")

SIZE = 96
STEPS = 50
EPISODES = 2
SEED = 5
ENV = {"type": "pusht", "observation_height": SIZE, "observation_width": SIZE}


def _our_episodes(ckpt: Path, tmp_path: Path) -> tuple[list[list[np.ndarray]], list]:
    from pipeline.execution.runner import plan_run
    from pipeline.planning.config import config_from_dict
    from workers.actor import EpisodeWorker

    cfg = config_from_dict(
        {
            "name": "pusht_parity",
            "backbone": {"kind": "lerobot", "params": {"path": str(ckpt)}},
            "env": {"suite": "lerobot", "params": {**ENV, "episode_length": STEPS}},
            "episodes_per_task": EPISODES,
            "seed": SEED,
            "grid": [{"mode": ["baseline"]}],
            "executor": {"kind": "inline"},
            "tracking": {"enabled": False},
        }
    )
    plan = plan_run(cfg, tmp_path / "run")
    assert plan.worker_spec.replan_steps == 5  # the checkpoint's n_action_steps
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
    finally:
        worker.close()
    return actions, rows


@pytest.mark.slow
def test_the_lerobot_suite_gives_lerobot_evals_pusht_episodes(tmp_path) -> None:
    from lerobot.envs.configs import PushtEnv

    ckpt = build_act(
        tmp_path / "act", image=SIZE, state=2, action=2, cams=("image!",), chunk=10,
        n_action_steps=5,
    )  # fmt: skip
    ours, rows = _our_episodes(ckpt, tmp_path)
    theirs, info = lerobot_eval_env(
        PushtEnv(**{k: v for k, v in ENV.items() if k != "type"}, episode_length=STEPS),
        ckpt,
        episodes=EPISODES,
        seed=SEED,
    )
    assert len(theirs) == len(ours) == EPISODES
    for e, (a, b, row) in enumerate(zip(theirs, ours, rows, strict=True)):
        assert len(a["actions"]) == len(b) == row.steps, f"episode {e}: lengths"
        for t, (x, y) in enumerate(zip(a["actions"], b, strict=True)):
            assert np.array_equal(x.astype(np.float32), y), f"episode {e} step {t}: {x} vs {y}"
        assert bool(info["per_task"][0]["metrics"]["successes"][e]) == row.success
    # the two episodes start apart (seed + e) and the actions follow the observation
    assert not np.array_equal(ours[0][0], ours[1][0])
    assert np.ptp(np.stack(ours[0]), axis=0).max() > 0.1  # not one constant action
