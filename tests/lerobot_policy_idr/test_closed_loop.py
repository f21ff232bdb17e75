"""Closed loop on PushT: the idr policy as lerobot-eval runs it (its rollout, an IDR folder)
and idr-eval's cell of the same mode, each on its defaults (executed horizon, clipping, do(S)
centered), lerobot-eval fed the harness's step seeds: the same action at every step and the
same sidecar rows (diagnostics, forward rows, executed steps) at every inference.

Here: the methods beside IDR that lerobot's tools run through the policy (temporal ensembling on
ACT, sample ensembling on Diffusion under DDIM with two observation steps), each with a control
that the method acted, and E on a base of each sampling family not covered closed loop
elsewhere (SmolVLA: shared noise; X-VLA: a seeded RNG), and image guidance (cfg, two of the
three passes) on the seeded base. ACT (deterministic) and Diffusion
(shared noise) under E: ``tests/workers/envs/test_lerobot_env_parity.py``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
from idr_core.sidecar import read_sidecar

from tests.lerobot_policy_idr.conftest import make_idr
from tests.workers.envs.test_lerobot_env_parity import (
    _assert_same_episodes,
    _harness_seeds,
    _lerobot_eval_with_seeds,
    _needs,
    _our_episodes,
)

pytestmark = [pytest.mark.slow, _needs("gym_pusht", "gym-pusht")]
STEPS = 24  # control steps of the one episode each side runs
DIAGNOSTICS = ("e_img", "e_prop", "r_img", "gate", "w_prop")


def _both_sides(
    tmp_path: Path,
    ckpt: Path,
    cell: dict[str, Any],
    *,
    replan: int,
    env_own_processors: bool = False,
) -> tuple[list, Any]:
    """One PushT episode of ``ckpt`` under ``cell`` in idr-eval and in lerobot-eval (an IDR
    folder of the same settings), asserted action for action; the harness's step rows and the
    plugin's sidecar rows."""
    from lerobot.envs.configs import PushtEnv

    args = [a for k, v in cell.items() for a in (f"--{k.replace('_', '-')}", str(v))]
    diag = tmp_path / "sidecar"
    folder = make_idr(ckpt, tmp_path / "idr", *args, "--diagnostics-dir", str(diag))
    env = {"observation_height": 96, "observation_width": 96, "episode_length": STEPS}
    steps: list = []
    ours, rows = _our_episodes(
        ckpt, tmp_path, {"type": "pusht", **env}, replan=replan, cell=cell, episodes=1, steps=steps
    )
    every = 1 if cell["mode"] == "temporal" else replan
    theirs, info = _lerobot_eval_with_seeds(
        PushtEnv(**env),
        folder,
        _harness_seeds(rows, replan=every),
        episodes=1,
        env_own_processors=env_own_processors,
    )
    assert rows[0].steps == STEPS
    _assert_same_episodes(theirs, info, ours, rows, moves=0.01)
    return steps[0], read_sidecar(diag)


def _acted(steps: list) -> bool:
    """Whether the executed action differs from the base's own at some inference."""
    return any(s.action_final != s.action_base for s in steps)


def test_temporal_ensembling_on_act_is_the_harness_cell_in_lerobot_eval(tmp_path) -> None:
    """lerobot's ACTTemporalEnsembler over chunks of the 5 executed actions, an inference at
    every step: one sidecar row per step, one forward row each."""
    from training.toy_checkpoints import build_act

    ckpt = build_act(
        tmp_path / "act", image=96, state=2, action=2, cams=("image!",), chunk=10,
        n_action_steps=5,
    )  # fmt: skip
    steps, sidecar = _both_sides(tmp_path, ckpt, {"mode": "temporal"}, replan=5)
    assert len(steps) == len(sidecar) == STEPS
    assert (sidecar["pass_rows"] == 1).all() and (sidecar["executed_steps"] == 1).all()
    assert steps[0].action_final == steps[0].action_base  # one chunk: nothing to average yet
    assert _acted(steps)  # then the average is not the current chunk's first action


def test_sample_ensembling_on_diffusion_is_the_harness_cell_in_lerobot_eval(tmp_path) -> None:
    """Three draws of Diffusion (DDIM, two observation steps) in one forward, each with the
    noise of its seed (``idr_core.methods.sample_seeds``), averaged and clipped."""
    from training.toy_checkpoints import build_diffusion

    ckpt = build_diffusion(
        tmp_path / "diffusion", image=96, state=2, action=2, n_obs_steps=2, cams=("image!",)
    )
    steps, sidecar = _both_sides(tmp_path, ckpt, {"mode": "ensemble"}, replan=4)
    assert len(steps) == len(sidecar) == STEPS // 4
    assert (sidecar["pass_rows"] == 3).all() and (sidecar["executed_steps"] == 4).all()
    assert all(s.pass_rows == 3 for s in steps)
    assert _acted(steps)  # the mean is not the first draw (the baseline's chunk)


@pytest.mark.parametrize("family", ["smolvla", "xvla"])
def test_E_on_each_sampling_family_is_the_harness_cell_in_lerobot_eval(tmp_path, family) -> None:
    """SmolVLA (one noise draw shared by the three thirds of one forward) and X-VLA (three
    forwards under one seed), random weights: actions and diagnostics bit for bit. lerobot-eval
    gives any X-VLA policy LIBERO's env processors; on PushT it runs with PushT's own."""
    from training.toy_checkpoints import build_local_tokenizer, build_smolvla
    from training.toy_xvla_checkpoint import build_xvla

    if family == "smolvla":
        ckpt = build_smolvla(tmp_path / "smolvla", image=96, state=2, action=2)
    else:
        tok = build_local_tokenizer(tmp_path / "tok", ["push the t"])
        ckpt = build_xvla(tmp_path / "xvla", tok, image=96, state=2, action=2, cams=("image!",))
    steps, sidecar = _both_sides(
        tmp_path, ckpt, {"mode": "E", "tau": 1e9}, replan=4, env_own_processors=family == "xvla"
    )
    assert len(steps) == len(sidecar) == STEPS // 4
    for key in DIAGNOSTICS:
        ours = np.float32([getattr(s, key) for s in steps])
        np.testing.assert_array_equal(sidecar[key].to_numpy().astype(np.float32), ours, key)
    assert (sidecar["e_img"] > 0).all() and _acted(steps)  # refined: not a vacuous comparison


def test_cfg_on_a_seeded_base_is_the_harness_cell_in_lerobot_eval(tmp_path) -> None:
    """Image guidance reads the factual and the image-zeroed passes alone. On X-VLA (three
    forwards under one seed) the plugin still draws each pass's noise as the whole tripled
    batch would, as the harness does: the same action at every step, the same rows counted."""
    from training.toy_checkpoints import build_local_tokenizer
    from training.toy_xvla_checkpoint import build_xvla

    tok = build_local_tokenizer(tmp_path / "tok", ["push the t"])
    ckpt = build_xvla(tmp_path / "xvla", tok, image=96, state=2, action=2, cams=("image!",))
    steps, sidecar = _both_sides(
        tmp_path, ckpt, {"mode": "cfg", "tau": 1e9}, replan=4, env_own_processors=True
    )
    assert len(steps) == len(sidecar) == STEPS // 4
    assert sidecar["pass_rows"].tolist() == [s.pass_rows for s in steps]
    assert _acted(steps)  # guided: not the base's own chunk
