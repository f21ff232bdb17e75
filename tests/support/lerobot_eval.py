"""lerobot-eval's own code path (LIBERO, PushT...), recording what reaches the simulator: its env config
and ``make_env``, ``make_policy``, its policy and env processors and ``eval_policy_all`` (what
``lerobot-eval`` runs), with a vector-env wrapper that records each step's action (and, if
asked, the simulator state after it). The parity tests compare idr-eval's episodes with these."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np


def sim_state(sim: Any) -> np.ndarray:
    """qpos, qvel (and time) of a robosuite simulator, flattened."""
    return np.asarray(sim.get_state().flatten()).copy()


def lerobot_eval_libero(
    policy_dir: Path,
    *,
    steps: int,
    episodes: int,
    seed: int,
    size: int,
    states: bool = False,
) -> tuple[list[dict[str, list[np.ndarray]]], dict]:
    """Episodes of ``libero_spatial/0`` as lerobot-eval runs them for the checkpoint (or idr
    folder) in ``policy_dir``: per episode ``{"actions": [...], "states": [...]}``; and
    eval_policy_all's info."""
    from lerobot.envs.configs import LiberoEnv as LiberoEnvConfig

    env_cfg = LiberoEnvConfig(
        task="libero_spatial",
        task_ids=[0],
        episode_length=steps,
        observation_height=size,
        observation_width=size,
    )

    def libero_state(vec: Any) -> np.ndarray:
        return sim_state(vec.unwrapped.envs[0].unwrapped._env.sim)

    return lerobot_eval_env(
        env_cfg, policy_dir, episodes=episodes, seed=seed, state=libero_state if states else None
    )


def lerobot_eval_env(
    env_cfg: Any,
    policy_dir: Path,
    *,
    episodes: int,
    seed: int,
    state: Any = None,
    max_steps: int | None = None,
    env_own_processors: bool = False,
) -> tuple[list[dict[str, list[np.ndarray]]], dict]:
    """Episodes of lerobot's env config ``env_cfg`` as lerobot-eval runs them for the checkpoint
    in ``policy_dir``: per episode ``{"actions": [...], "states": [...]}`` (``state(vec_env)``
    after each step, when given); and eval_policy_all's info. ``max_steps``: the budget the
    rollout reads (``env.call("_max_episode_steps")``) for an env whose config does not set it
    (MetaWorld's is 500), as ``env.params.max_steps`` sets ours; the env is unchanged.
    ``env_own_processors``: the env config's own env processors, where lerobot-eval's
    ``make_env_pre_post_processors`` gives any X-VLA policy LIBERO's (its 6-D rotation
    postprocessor cannot act on another env's actions)."""
    import gc

    import gymnasium as gym
    import torch
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.envs.factory import make_env, make_env_pre_post_processors
    from lerobot.policies.factory import make_policy, make_pre_post_processors
    from lerobot.scripts.lerobot_eval import eval_policy_all

    recorded: list[dict[str, list[np.ndarray]]] = []

    class Recorder(gym.vector.VectorWrapper):
        """What reaches the simulator, step by step (lerobot's rollout is unchanged)."""

        def reset(self, **kwargs):
            out = self.env.reset(**kwargs)
            recorded.append({"actions": [], "states": []})
            return out

        def call(self, name, *args, **kwargs):
            if name == "_max_episode_steps" and max_steps is not None:
                return (max_steps,) * self.env.num_envs
            return self.env.call(name, *args, **kwargs)

        def step(self, actions):
            out = self.env.step(actions)
            recorded[-1]["actions"].append(np.array(actions[0], copy=True))
            if state is not None:
                recorded[-1]["states"].append(state(self.env))
            return out

    from workers.rendering import release_gl_context

    # a MuJoCo env an earlier test left to the collector frees its GL objects under whichever
    # context is current when it is collected: collected now, not in the middle of this
    # reference run (where it would delete this env's framebuffer: black frames from then on)
    gc.collect()
    envs = make_env(env_cfg, n_envs=1)
    envs = {suite: {tid: Recorder(v) for tid, v in m.items()} for suite, m in envs.items()}
    cfg = PreTrainedConfig.from_pretrained(policy_dir)
    cfg.pretrained_path = policy_dir
    cfg.device = "cpu"
    policy = make_policy(cfg, env_cfg=env_cfg).eval()
    pre, post = make_pre_post_processors(
        cfg,
        pretrained_path=str(policy_dir),
        preprocessor_overrides={"device_processor": {"device": "cpu"}},
    )
    if env_own_processors:
        env_pre, env_post = env_cfg.get_env_processors()
    else:
        env_pre, env_post = make_env_pre_post_processors(env_cfg, cfg)
    try:
        with torch.no_grad():
            info = eval_policy_all(
                envs=envs,
                policy=policy,
                env_preprocessor=env_pre,
                env_postprocessor=env_post,
                preprocessor=pre,
                postprocessor=post,
                n_episodes=episodes,
                start_seed=seed,
            )
    finally:
        for m in envs.values():
            for v in m.values():
                release_gl_context(v.env)
                v.close()
        sidecar = getattr(policy, "sidecar", None)
        if sidecar is not None:
            sidecar.flush()
    return recorded, info
