"""Small real lerobot checkpoints (random weights, built offline) and IDR folders around them."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from lerobot_policy_idr.loading import load_idr
from lerobot_policy_idr.wrap import main as wrap_main

from training.toy_checkpoints import build_act, build_diffusion


@pytest.fixture(scope="session")
def bases(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bases")
    return {
        "act": build_act(root / "act", n_action_steps=4),
        "diffusion": build_diffusion(root / "diffusion"),
    }


def make_idr(base: Path, out: Path, *args: str) -> Path:
    """An IDR folder around ``base`` made by the real command (exit code checked); its sidecar
    beside it unless ``args`` name one (not in the working directory's idr_diagnostics)."""
    if "--diagnostics-dir" not in args:
        args = (*args, "--diagnostics-dir", str(out.parent / f"{out.name}-diagnostics"))
    code = wrap_main([str(base), str(out), *args])
    assert code == 0, f"lerobot-idr-wrap exited {code}"
    return out


def obs_batch(b: int = 2, seed: int = 0, image: int = 64, state: int = 8) -> dict:
    """An env-side observation batch as lerobot-eval hands it to the preprocessor."""
    g = torch.Generator().manual_seed(seed)
    return {
        "observation.images.agentview": torch.rand(b, 3, image, image, generator=g),
        "observation.state": 0.5 + torch.rand(b, state, generator=g),
        "task": [f"task {i}" for i in range(b)],
    }


def rollout(policy, pre, post, steps: int) -> list[torch.Tensor]:
    """select_action on a sequence of observations (2 envs, seeds 0..steps-1), as lerobot-eval's
    loop calls it, from a reset."""
    policy.reset()
    out = []
    for t in range(steps):
        with torch.inference_mode():
            out.append(post(policy.select_action(pre(obs_batch(2, seed=t)))))
    return out


def seeded_chunks(idr, base, obs: dict, seeds=(11, 12)) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per seed: the IDR policy's chunk with that seed given as its noise (the forked-RNG
    path), and the base's own chunk under the same torch seed, cut to the IDR policy's
    n_action_steps. ``idr``, ``base``: (policy, pre, post)."""
    (policy, pre, post), (theirs, pre0, post0) = idr, base
    out = []
    for seed in seeds:
        with torch.inference_mode():
            ours = post(policy.predict_action_chunk(pre(dict(obs)), noise=torch.tensor([seed])))
            torch.manual_seed(seed)
            chunk = post0(theirs.predict_action_chunk(pre0(dict(obs))))
        out.append((ours, chunk[:, : policy.n_action_steps]))
    return out


def load(folder: Path):
    """The policy and its processors from an IDR folder, as lerobot's tools load it."""
    return load_idr(folder)
