"""``python -m training.zoo export``: a member's last checkpoint copied to where the harness
loads it, with ``train_meta.json`` beside it (steps, seed, wall time, machines, the dataset; a
checkpoint trained in stages: totals and each stage's figures)."""

from __future__ import annotations

import argparse
import json
import shutil

from training.zoo_benchmarks import BENCHMARKS, last_checkpoint, run_dir
from training.zoo_members import member_named, stage_flags


def cmd_export(args: argparse.Namespace) -> None:
    member = member_named(args.name)
    out = run_dir(args.name, args.seed, args.runs, args.init_from)
    last = last_checkpoint(out)
    if last is None:
        raise SystemExit(
            f"no checkpoint of {args.name!r} under {out}; train it first: "
            f"python -m training.zoo train {args.name}"
        )
    dest = args.dest or BENCHMARKS[args.benchmark].shipped / args.name
    # read before dest is replaced: a continued stage is usually exported over its start
    before = None
    if args.init_from is not None:
        before = json.loads((args.init_from / "train_meta.json").read_text())
    if dest.exists():
        shutil.rmtree(dest)
    shutil.copytree(last / "pretrained_model", dest)
    (dest / "train_config.json").unlink(missing_ok=True)  # holds this machine's paths
    # lerobot-train records the folder it loaded from in the config (--policy.path for a
    # continued stage, the run's own checkpoint on --resume): a path on this machine, not the
    # checkpoint's (a continued stage's start is in train_meta's stages)
    cfg_file = dest / "config.json"
    cfg = json.loads(cfg_file.read_text())
    if cfg.get("pretrained_path") is not None:
        cfg["pretrained_path"] = None
        cfg_file.write_text(json.dumps(cfg, indent=4) + "\n")
    step = json.loads((last / "training_state" / "training_step.json").read_text())["step"]
    sessions = [
        json.loads(line) for line in (out / "zoo_sessions.jsonl").read_text().splitlines() if line
    ]
    from safetensors.torch import load_file

    params = sum(t.numel() for t in load_file(dest / "model.safetensors").values())
    parts = args.dataset / "meta" / "zoo_parts.json"
    meta = {
        "member": args.name,
        "policy_type": member.policy_type,
        "language": member.language,
        "flags": list(member.flags) if before is None else stage_flags(member.flags, step),
        "batch_size": member.batch_size,
        "steps": step,
        "seed": args.seed,
        "params": params,
        "train_seconds": round(sum(s["seconds"] for s in sessions), 1),
        "sessions": len(sessions),
        "machines": sorted({s["cpu"] for s in sessions}),
        "devices": sorted({s.get("device", "cpu") for s in sessions}),
        "threads": sorted({s["threads"] for s in sessions}),
        "dataset": json.loads(parts.read_text()) if parts.is_file() else str(args.dataset),
        "trainer": "lerobot-train (lerobot 0.6.1) via python -m training.zoo train",
    }
    if before is not None:
        meta = continued_meta(before, meta)
    (dest / "train_meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    print(json.dumps(meta, indent=2))


def continued_meta(before: dict, stage: dict) -> dict:
    """The card data of a checkpoint trained in stages: totals over the stages (steps, wall time,
    sessions, machines), each stage's own figures under ``stages`` (the first stage's included),
    and the last stage's flags and dataset."""
    stages = before.get("stages") or [_stage(before)]
    return {
        **stage,
        "steps": before["steps"] + stage["steps"],
        "train_seconds": round(before["train_seconds"] + stage["train_seconds"], 1),
        "sessions": before["sessions"] + stage["sessions"],
        "machines": sorted({*before["machines"], *stage["machines"]}),
        "devices": sorted({*before.get("devices", ["cpu"]), *stage["devices"]}),
        "threads": sorted({*before["threads"], *stage["threads"]}),
        "stages": [*stages, {**_stage(stage), "init_from": "the stage before's weights"}],
    }


def _stage(meta: dict) -> dict:
    data = meta["dataset"]
    return {
        "steps": meta["steps"],
        "train_seconds": meta["train_seconds"],
        "machines": meta["machines"],
        "threads": meta["threads"],
        "dataset_frames": data.get("frames") if isinstance(data, dict) else data,
        "flags": meta["flags"],
    }
