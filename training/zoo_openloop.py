"""A checkpoint's next action on its own dataset's frames: the open-loop error.

A policy that predicts the demonstrations' next action well on their frames but fails
closed-loop has learned a shortcut the frames allow and its own rollouts do not (the copycat
shortcut of the tabletop state's orientation dims, docs/zoo.md), or drifts out of the data. This
loads the checkpoint through lerobot's factory and its saved processors, runs ``select_action``
(queue reset, so each frame gets a fresh chunk) on ``--frames`` frames drawn with a fixed seed,
and reports the mean absolute error per action dim in the dataset's standard deviations, next to
the error of always predicting the dataset's mean action. Dims that never vary in the data
(std 0) are left out.

    python -m training.zoo_openloop checkpoints/zoo/tiny_vla --dataset data/zoo/tabletop
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from idr_core.features import ACTION, OBS_PREFIX


def open_loop_error(
    checkpoint: Path, dataset: Path, frames: int = 100, seed: int = 0, keep_actions: bool = False
) -> dict:
    import torch
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import get_policy_class
    from lerobot_policy_idr.processor_idr import load_base_processors  # (registers tiny_vla)

    cfg = PreTrainedConfig.from_pretrained(checkpoint)
    policy = get_policy_class(cfg.type).from_pretrained(checkpoint).eval()
    pre, post = load_base_processors(checkpoint, str(policy.config.device))
    ds = LeRobotDataset("local/openloop", root=dataset)
    stats = ds.meta.stats[ACTION]
    mean, std = np.asarray(stats["mean"]), np.asarray(stats["std"])
    varies = std > 1e-6
    rng = np.random.default_rng(seed)
    errors, baseline, actions = [], [], []
    for n, i in enumerate(rng.choice(len(ds), size=min(frames, len(ds)), replace=False)):
        frame = ds[int(i)]
        obs = {k: v.unsqueeze(0) for k, v in frame.items() if k.startswith(OBS_PREFIX)}
        obs["task"] = [frame["task"]]
        policy.reset()
        torch.manual_seed(seed + n)  # a sampling head draws the same noise for every checkpoint
        with torch.no_grad():
            action = post(policy.select_action(pre(obs))).squeeze(0).numpy()
        truth = frame[ACTION].numpy()
        errors.append(np.abs(action - truth)[varies] / std[varies])
        actions.append(action[varies] / std[varies])
        baseline.append(np.abs(mean - truth)[varies] / std[varies])
    err, base = np.mean(errors, axis=0), np.mean(baseline, axis=0)
    return {
        "checkpoint": str(checkpoint),
        "dataset": str(dataset),
        "frames": len(errors),
        "dims": [int(d) for d in np.flatnonzero(varies)],
        "mae_in_std": [round(float(x), 3) for x in err],
        "mean_action_mae_in_std": [round(float(x), 3) for x in base],
        "ratio_to_mean_action": round(float(err.mean() / base.mean()), 3),
        **({"actions_in_std": np.asarray(actions).tolist()} if keep_actions else {}),
    }


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoint", type=Path)
    ap.add_argument("--dataset", type=Path, default=Path("data/zoo/tabletop"))
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    print(json.dumps(open_loop_error(args.checkpoint, args.dataset, args.frames, args.seed)))


if __name__ == "__main__":
    main()
