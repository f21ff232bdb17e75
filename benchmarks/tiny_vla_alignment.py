"""Where a tiny VLA fails stack_color: how close it brings the held cube to its goal, and whether
its carry actions point where the expert's do, by distance to the goal.

The scripted expert labels every visited state (it is a stateless feedback rule), so each of the
policy's inferences while it carries the top cube can be compared with what the expert would do
there. A policy that localizes the goal well turns its xy action toward the expert's as the
distance shrinks; one that cannot settles, or circles, a few centimetres away with actions that
no longer agree with the expert's (cosine near 0 or negative). Writes
``benchmarks/results/tiny_vla_alignment.json``.

Usage: ``python benchmarks/tiny_vla_alignment.py [--checkpoints checkpoints/tiny_vla ...]
[--episodes 10] [--seed 1]`` (seed 0 is the default run's: keep it out of checkpoint selection).
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path
from typing import Any

import numpy as np

RESULTS = Path(__file__).parent / "results" / "tiny_vla_alignment.json"
BINS_CM = (0.0, 1.0, 2.0, 4.0, 8.0, np.inf)  # xy distance of the held cube to its goal


def rollout(env: Any, backbone: Any, episode: int, seed: int, replan: int) -> dict[str, Any]:
    """One stack_color episode driven by the policy; per inference while the top cube is held
    and lifted: (distance to the goal in cm, policy xy action, expert xy action)."""
    from workers.envs.suites.tabletop.layout import TABLE_TOP_Z
    from workers.episode.observation import to_policy_observation
    from workers.experts.tabletop import CARRY_Z, expert_action

    obs = env.reset("stack_color", episode, seed)
    backbone.reset()
    carry: list[tuple[float, list[float], list[float], float]] = []
    queue: list[np.ndarray] = []
    while not obs.status.done:
        if not queue:
            batch = to_policy_observation(obs, obs.status.instruction, backbone.cameras)
            queue = list(backbone.predict_chunk(batch)[0, :replan].numpy())
            priv = obs.privileged
            top, bottom = priv["targets"]
            pos = np.asarray(priv["cube_pos"])
            # carrying: the held cube above the height at which the expert stops lifting it and
            # travels (below it, the expert's label is "lift", with no xy motion to compare)
            if priv["grasped"][top] and pos[top, 2] >= TABLE_TOP_Z + CARRY_Z:
                d_cm = float(np.linalg.norm(pos[top, :2] - pos[bottom, :2]) * 100)
                (other,) = set(range(len(pos))) - {top, bottom}  # the cube not named
                d_other = float(np.linalg.norm(pos[top, :2] - pos[other, :2]) * 100)
                label = expert_action(priv)
                carry.append((d_cm, queue[0][:2].tolist(), label[:2].tolist(), d_other))
        obs = env.step(queue.pop(0))
    return {"success": bool(obs.status.success), "steps": obs.status.steps, "carry": carry}


def summarize(episodes: list[dict[str, Any]]) -> dict[str, Any]:
    rows = [c for e in episodes for c in e["carry"]]
    d = np.array([r[0] for r in rows])
    pol = np.array([r[1] for r in rows]).reshape(-1, 2)
    exp = np.array([r[2] for r in rows]).reshape(-1, 2)
    bins = []
    for lo, hi in itertools.pairwise(BINS_CM):
        m = (d >= lo) & (d < hi)
        if not m.any():
            continue
        p, e = pol[m], exp[m]
        cos = (p * e).sum(1) / (np.linalg.norm(p, axis=1) * np.linalg.norm(e, axis=1) + 1e-9)
        bins.append(
            {
                "distance_cm": [lo, None if np.isinf(hi) else hi],
                "inferences": int(m.sum()),
                "policy_xy_norm": float(np.linalg.norm(p, axis=1).mean()),
                "expert_xy_norm": float(np.linalg.norm(e, axis=1).mean()),
                "cosine_mean": float(cos.mean()),
            }
        )
    # where failed episodes end up: the median distance over their last 10 carry inferences, to
    # the goal and to the cube the instruction does not name
    failed = [e for e in episodes if not e["success"]]
    failed_ends = [float(np.median([c[0] for c in e["carry"][-10:]])) for e in failed if e["carry"]]
    other_ends = [float(np.median([c[3] for c in e["carry"][-10:]])) for e in failed if e["carry"]]
    near = 4.0  # cm: "at" a cube (cubes are placed at least 8 cm apart)
    outcomes = {
        "success": sum(e["success"] for e in episodes),
        "failed_never_carried": sum(not e["carry"] for e in failed),
        "failed_ended_near_goal": sum(d < near for d in failed_ends),
        "failed_ended_near_other_cube": sum(
            o < near <= d for d, o in zip(failed_ends, other_ends, strict=True)
        ),
        "failed_ended_elsewhere": sum(
            d >= near and o >= near for d, o in zip(failed_ends, other_ends, strict=True)
        ),
    }
    return {
        "episodes": len(episodes),
        "success_rate": float(np.mean([e["success"] for e in episodes])),
        "carry_inferences": len(rows),
        "share_within_2cm": float((d < 2.0).mean()) if len(d) else None,
        "outcomes": outcomes,
        "failed_end_distance_cm": sorted(round(x, 2) for x in failed_ends),
        "episodes_with_carry": sum(bool(e["carry"]) for e in episodes),
        "by_distance": bins,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoints", nargs="+", default=["checkpoints/tiny_vla"])
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--replan-steps", type=int, default=4)
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()

    from workers.rendering import configure_rendering

    configure_rendering()
    from workers.backbones.lerobot.adapter import LerobotBackbone
    from workers.envs.suites.tabletop.env import TabletopEnv

    env = TabletopEnv(image_size=96, cameras=("agentview", "wrist"))
    out: dict[str, Any] = {
        "task": "stack_color",
        "seed": args.seed,
        "replan_steps": args.replan_steps,
        "checkpoints": {},
    }
    try:
        for ck in args.checkpoints:
            backbone = LerobotBackbone(path=ck, device="cpu")
            t0 = time.perf_counter()
            eps = [
                rollout(env, backbone, i, args.seed, args.replan_steps)
                for i in range(args.episodes)
            ]
            out["checkpoints"][ck] = {**summarize(eps), "seconds": time.perf_counter() - t0}
            print(json.dumps({ck: out["checkpoints"][ck]}, indent=1), flush=True)
    finally:
        env.close()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
