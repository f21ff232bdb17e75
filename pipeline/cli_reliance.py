"""``idr-eval reliance``: open-loop reliance of a benchmark's members on one shared set of
held-out demonstration frames (``pipeline.reporting.reliance``)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError


def _members(items: list[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in items:
        name, eq, path = item.partition("=")
        if not eq or not name or not path:
            raise ConfigError(f"--member {item!r}: write NAME=CHECKPOINT_FOLDER")
        if name in out:
            raise ConfigError(f"--member {name!r} given twice; each member once")
        if not Path(path).is_dir():
            raise ConfigError(f"--member {name}={path}: no such checkpoint folder")
        out[name] = path
    if not out:
        raise ConfigError("give at least one --member NAME=CHECKPOINT_FOLDER")
    return out


def _cmd_reliance(args: argparse.Namespace) -> int:
    from idr_core.interventions import InterventionConfig

    from pipeline.api.frames import dataset_frames
    from pipeline.api.reliance import run
    from pipeline.reporting.reliance import RELIANCE_MD

    members = _members(args.member)  # every check before the frames are read
    if args.strategies is not None and args.strategies not in members:
        raise ConfigError(
            f"--strategies {args.strategies!r}: not a member; the members are {sorted(members)}"
        )
    gripper = None if args.gripper_dim == "none" else int(args.gripper_dim)
    try:
        iv = InterventionConfig(strategy=args.strategy, state_space=args.state_space)
    except ValueError as e:
        raise ConfigError(str(e)) from None
    frames = dataset_frames(args.frames, every=args.every, gripper_dim=gripper)
    out = Path(args.out)
    run(
        members,
        frames,
        out,
        intervention=iv,
        strategies_member=args.strategies,
        batch_size=args.batch_size,
        seed=args.seed,
    )
    print((out / RELIANCE_MD).read_text())
    return 0


def add_reliance(sub: Any) -> None:
    rel = sub.add_parser(
        "reliance",
        help="open-loop E_img, E_prop, R_img of several checkpoints on one set of held-out "
        "demonstration frames, by progress fifth and gripper phase",
    )
    rel.add_argument("frames", help="a local LeRobotDataset of held-out demonstrations")
    rel.add_argument(
        "--member",
        action="append",
        default=[],
        metavar="NAME=CHECKPOINT",
        help="a member and its checkpoint folder (repeat)",
    )
    rel.add_argument("--out", required=True, help="where reliance.{md,json} go")
    rel.add_argument("--every", type=int, default=1, help="every k-th frame of each episode")
    rel.add_argument(
        "--gripper-dim",
        default="-1",
        help="the action dim of the gripper command (> 0 closes), or none",
    )
    rel.add_argument("--strategy", default="zero", help="do(V) and do(S): zero, mean, gaussian")
    rel.add_argument("--state-space", default="centered", help="do(S): centered, raw, normalized")
    rel.add_argument(
        "--strategies",
        metavar="MEMBER",
        help="also measure this member under every strategy (zero, mean, gaussian)",
    )
    rel.add_argument("--batch-size", type=int, default=32)
    rel.add_argument("--seed", type=int, default=0)
    rel.set_defaults(func=_cmd_reliance)
