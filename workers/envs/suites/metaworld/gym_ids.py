"""MetaWorld v3 tasks as a Gymnasium id whose scene is a function of the reset seed.

Importing this module registers ``idr/MetaWorld-v3`` (``env.params.id:
"workers.envs.suites.metaworld.gym_ids:idr/MetaWorld-v3"`` in the gymnasium suite). Why not
metaworld's own ids: ``Meta-World/MT1`` draws the task (object and goal positions) from its RNG
*before* the reset's seed is applied, so the same seed gives a different scene depending on the
episodes before it; ``Meta-World/goal_observable`` takes no render size. This id builds the
task's env class as lerobot's MetaWorld env does (``MT1(...).train_classes``) (object positions drawn from the reset's seed:
``seeded_rand_vec``), at the render size and camera given, under metaworld's step limit.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

ENV_ID = "idr/MetaWorld-v3"


class SeededMetaWorld(gym.Wrapper):
    """Reseeds the task's position sampler at every ``reset(seed=...)``."""

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> Any:
        if seed is not None:
            self.env.unwrapped.seed(seed)
        return self.env.reset(seed=seed, options=options)


def make(
    env_name: str,
    render_mode: str | None = "rgb_array",
    width: int = 480,
    height: int = 480,
    camera_name: str = "corner2",
    max_episode_steps: int | None = None,
) -> gym.Env:
    import metaworld

    if env_name not in metaworld.ALL_V3_ENVIRONMENTS:
        import difflib

        close = difflib.get_close_matches(env_name, list(metaworld.ALL_V3_ENVIRONMENTS), n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise ValueError(f"env_name={env_name!r} is not a MetaWorld v3 task{hint}")
    mt1 = metaworld.MT1(env_name, seed=0)  # the task's class and a task to start from
    env = mt1.train_classes[env_name](
        render_mode=render_mode, camera_name=camera_name, width=width, height=height
    )
    env.set_task(mt1.train_tasks[0])
    env._freeze_rand_vec = False  # a new scene at every reset ...
    env.seeded_rand_vec = True  # ... drawn from the reset's seed
    return gym.wrappers.TimeLimit(SeededMetaWorld(env), max_episode_steps or env.max_path_length)


if ENV_ID not in gym.registry:
    gym.register(ENV_ID, entry_point=make)
