"""CALVIN's official evaluation sequences and the initial scene of each, as the official code
makes them (``calvin_models/calvin_agent/evaluation/multistep_sequences.py`` and
``get_env_state_for_initial_condition``): numpy only, no simulator.

The 1000 sequences of ``multistep_sequences.get_sequences(1000)`` are shipped in
``data/calvin_eval_sequences.json`` beside this module; episode ``e`` is sequence ``e``: an
initial condition and five subtasks, each run for at most ``EP_LEN`` steps.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

import numpy as np

SEQUENCES_FILE = Path(__file__).parent / "data" / "calvin_eval_sequences.json"
EP_LEN = 360  # steps per subtask (evaluate_policy.py)
NUM_SUBTASKS = 5

# the official neutral robot pose (tcp pos, euler, gripper width, 7 joints, gripper action)
NEUTRAL_ROBOT_OBS = np.array(
    [
        *(0.02586889, -0.2313129, 0.5712808, 3.09045411, -0.02908596, 1.50013585, 0.07999963),
        *(-1.21779124, 1.03987629, 2.11978254, -2.34205014, -0.87015899, 1.64119093, 0.55344928),
        1.0,
    ]
)
BLOCK_SLIDER_LEFT = np.array([-2.40851662e-01, 9.24044687e-02, 4.60990009e-01])
BLOCK_SLIDER_RIGHT = np.array([7.03416330e-02, 9.24044687e-02, 4.60990009e-01])
BLOCK_TABLE = (
    np.array([5.00000896e-02, -1.20000177e-01, 4.59990009e-01]),
    np.array([2.29995412e-01, -1.19995140e-01, 4.59990010e-01]),
)
BLOCK_ROT_Z = (np.pi / 2 - np.pi / 8, np.pi / 2 + np.pi / 8)


def fnv1_32(text: str) -> int:
    """The hash the official code seeds scenes with: pyhash's ``fnv1_32()``, which is FNV-1
    (multiply by the FNV prime, then xor) from 0, not from the FNV offset basis, over the
    string's UTF-16-LE bytes. Written here because pyhash does not build on Python >= 3.11."""
    h = 0
    for byte in text.encode("utf-16-le"):
        h = ((h * 0x01000193) & 0xFFFFFFFF) ^ byte
    return h


def condition_seed(condition: dict[str, Any]) -> int:
    """The scene seed of an initial condition: the hash of ``str(dict.values())`` (so the key
    order matters: led, lightbulb, slider, drawer, red_block, blue_block, pink_block, grasped)."""
    return fnv1_32(str(condition.values()))


def initial_state(condition: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(robot_obs 15-d, scene_obs 24-d) of an initial condition, as the official
    ``get_env_state_for_initial_condition`` (numpy's legacy MT19937 stream, same draws)."""
    rng = np.random.RandomState(condition_seed(condition))
    table = list(BLOCK_TABLE)
    rng.shuffle(table)
    on_slider = {"slider_left": BLOCK_SLIDER_LEFT, "slider_right": BLOCK_SLIDER_RIGHT}
    scene = np.zeros(24)
    if condition["slider"] == "left":
        scene[0] = 0.28
    if condition["drawer"] == "open":
        scene[1] = 0.22
    if condition["lightbulb"] == 1:
        scene[3] = 0.088
    scene[4] = condition["lightbulb"]
    scene[5] = condition["led"]
    scene[6:9] = on_slider.get(condition["red_block"], table[0])
    scene[11] = rng.uniform(*BLOCK_ROT_Z)
    if condition["blue_block"] in on_slider:
        scene[12:15] = on_slider[condition["blue_block"]]
    else:
        scene[12:15] = table[1] if condition["red_block"] == "table" else table[0]
    scene[17] = rng.uniform(*BLOCK_ROT_Z)
    scene[18:21] = on_slider.get(condition["pink_block"], table[1])
    scene[23] = rng.uniform(*BLOCK_ROT_Z)
    return NEUTRAL_ROBOT_OBS.copy(), scene


@functools.lru_cache(maxsize=4)
def load_sequences(path: str | None = None) -> tuple[tuple[dict[str, Any], tuple[str, ...]], ...]:
    """The evaluation sequences: (initial condition, five subtask names), in the official order."""
    data = json.loads(Path(path or SEQUENCES_FILE).read_text())
    return tuple((dict(cond), tuple(tasks)) for cond, tasks in data)
