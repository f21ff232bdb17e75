"""The zoo: lerobot architectures trained by lerobot's own trainer on the same demonstrations.

One launcher for every member, so a run is resumable across sessions and every checkpoint is
made the same way:

    python -m training.zoo train act          # lerobot-train, resumed from its last checkpoint
    python -m training.zoo export act         # checkpoints/zoo/act: the last checkpoint + card data
    python -m training.zoo list               # members, their flags and their state
    python -m training.zoo train smolvla --init-from checkpoints/zoo/tabletop_pos/smolvla --steps 5000
    python -m training.zoo train act --eval-every 1000  # + evaluation during training

``--init-from`` continues training from an exported checkpoint's weights (lerobot-train's own
``--policy.path``: the weights and config are loaded, the optimizer and its schedule start
afresh, the normalization stats are the dataset's): how a member that was exported and whose run
folder is gone (a new session on a new machine) is trained on. Its run folder is
``NAME_seedS_continued``; ``export --init-from`` adds the stage to the checkpoint's card data.

``train`` runs ``lerobot-train`` (offline, CPU unless ``--device``) with the member's flags, and
``--resume=true`` when the run folder already holds a checkpoint: a session that is stopped
loses at most ``save_freq`` steps. The member's small widths are plain ``--policy.*`` flags; the
dataset's features are checked against the member before any work. ``export`` copies the
``pretrained_model`` folder of the last checkpoint (config, safetensors, processors: what
lerobot's factory loads) and writes ``train_meta.json`` beside it (steps, seed, wall time, the
machine's CPU, the dataset's summary). ``--eval-every`` evaluates the checkpoints as they are
saved, in a process of its own (``training/zoo_evaluator.py``).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from training.zoo_benchmarks import (  # noqa: F401  (zoo.BENCHMARKS etc. for callers)
    BENCHMARKS,
    DATASET,
    METAWORLD_FEATURES,
    ROOT,
    RUNS,
    SHIPPED,
    TABLETOP_FEATURES,
    TABLETOP_POS_FEATURES,
    Benchmark,
    offline_env,
)
from training.zoo_data import dataset_tasks
from training.zoo_hub import SMOLVLM, XVLA_TOKENIZER, install, repo_id, xvla_florence_config


@dataclass(frozen=True)
class Member:
    """One zoo architecture: its lerobot policy type and the flags that make it small."""

    policy_type: str
    flags: tuple[str, ...]
    steps: int  # training steps of the shipped checkpoint (sized to ~60-90 min of 2 cores)
    batch_size: int
    language: bool  # whether the class conditions on the instruction
    save_freq: int = 1000
    vocab: bool = False  # the class takes its instruction vocabulary from the dataset's tasks
    # flags for one benchmark only (the tiny VLA masks the tabletop state's orientation dims)
    benchmark_flags: dict[str, tuple[str, ...]] = field(default_factory=dict)


MEMBERS: dict[str, Member] = {
    # ACT from scratch (no ImageNet download): a 2+1-layer transformer of width 256 over a
    # ResNet-18 per camera; chunks of 8, 4 executed (as the tiny VLA). No instruction input.
    "act": Member(
        "act",
        (
            "--policy.pretrained_backbone_weights=null",
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
            "--policy.dim_model=256",
            "--policy.dim_feedforward=1024",
            "--policy.n_encoder_layers=2",
            "--policy.n_decoder_layers=1",
            "--policy.optimizer_lr=1e-4",
            "--policy.optimizer_lr_backbone=1e-4",
        ),
        steps=6000,
        batch_size=32,
        language=False,
        save_freq=500,
    ),
    # Diffusion Policy from scratch: a small 1-D UNet (64-128-256) over a ResNet-18 with group
    # norm (required without pretrained weights); DDIM with 10 steps, so the three IDR passes can
    # share their noise exactly. No instruction input.
    "diffusion": Member(
        "diffusion",
        (
            "--policy.pretrained_backbone_weights=null",
            "--policy.use_group_norm=true",
            "--policy.horizon=16",
            "--policy.n_action_steps=8",
            "--policy.down_dims=[64,128,256]",
            "--policy.noise_scheduler_type=DDIM",
            "--policy.num_inference_steps=10",
            "--policy.n_obs_steps=1",
        ),
        steps=6000,
        batch_size=32,
        language=False,
        save_freq=500,
    ),
    # X-VLA, the paper's backbone: Florence-2 at small widths (training/zoo_hub.py) reads both
    # cameras and the instruction; the state enters with the action tokens of a 3-layer
    # transformer of width 128 (flow matching, 10 denoising steps). Tokenizer by hub id from the
    # local cache (installed by make setup), so the checkpoint loads from any folder.
    "xvla": Member(
        "xvla",
        (
            "--policy.florence_config=" + json.dumps(xvla_florence_config(), separators=(",", ":")),
            f"--policy.tokenizer_name={repo_id(XVLA_TOKENIZER)}",
            "--policy.tokenizer_max_length=16",
            "--policy.hidden_size=128",
            "--policy.depth=3",
            "--policy.num_heads=4",
            "--policy.num_domains=1",
            "--policy.len_soft_prompts=4",
            "--policy.dim_time=16",
            "--policy.action_mode=auto",
            "--policy.num_denoising_steps=10",
            "--policy.max_state_dim=8",
            "--policy.max_action_dim=7",
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
            # one learning rate for every part: lerobot's X-VLA preset gives the VLM a tenth of
            # it, meant for fine-tuning pretrained Florence-2 weights; here they start random
            "--use_policy_training_preset=false",
            "--optimizer.type=adamw",
            "--optimizer.lr=3e-4",
            "--optimizer.weight_decay=0.0",
            "--optimizer.grad_clip_norm=10",
            "--scheduler.type=cosine_decay_with_warmup",
            "--scheduler.peak_lr=3e-4",
            "--scheduler.decay_lr=1e-5",
            "--scheduler.num_warmup_steps=200",
            "--scheduler.num_decay_steps=6000",
        ),
        steps=6000,
        batch_size=32,
        language=True,
        save_freq=500,
    ),
    # SmolVLA: SmolVLM2 at small widths (training/zoo_hub.py: a 2-layer vision tower, a
    # 4-layer Llama of width 64) built from its config (no weights) and trained whole, with its
    # flow-matching action expert; instruction, both cameras at 96 px, state as a token.
    "smolvla": Member(
        "smolvla",
        (
            f"--policy.vlm_model_name={repo_id(SMOLVLM)}",
            "--policy.load_vlm_weights=false",
            # random VLM weights: train everything (the defaults freeze the VLM for fine-tuning)
            "--policy.train_expert_only=false",
            "--policy.freeze_vision_encoder=false",
            "--policy.resize_imgs_with_padding=[96,96]",
            "--policy.tokenizer_max_length=16",
            "--policy.num_vlm_layers=4",
            "--policy.num_expert_layers=4",
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
            "--policy.num_steps=10",
            "--policy.max_state_dim=8",
            "--policy.max_action_dim=7",
            # lerobot's preset (1e-4 after 1,000 warmup steps, decay over 30,000) is meant for
            # fine-tuning pretrained SmolVLM weights; these start random and small
            "--policy.optimizer_lr=3e-4",
            "--policy.scheduler_warmup_steps=200",
            "--policy.scheduler_decay_steps=6000",
        ),
        steps=6000,
        batch_size=32,
        language=True,
        save_freq=500,
    ),
    # the tiny VLA (our plugin's type), by lerobot's trainer on the zoo's dataset: the net, the
    # masked orientation dims and the chunking of the shipped one (docs/tiny-vla.md)
    "tiny_vla": Member(
        "tiny_vla",
        (
            "--policy.chunk_size=8",
            "--policy.n_action_steps=4",
        ),
        steps=8000,
        batch_size=64,
        language=True,
        vocab=True,
        benchmark_flags={
            "tabletop": ("--policy.ignored_state_dims=[3,4,5]",),
            # runs where lerobot's MetaWorld env renders 480 px (the parity test)
            "metaworld": ("--policy.resize_images_to=96",),
        },
    ),
}


def vocab_flag(root: Path) -> str:
    from training.train_tiny_vla import vocabulary

    return "--policy.vocab=[" + ",".join(vocabulary(dataset_tasks(root))) + "]"


def dataset_features(
    root: Path, record: str = BENCHMARKS["tabletop"].record
) -> dict[str, list[int]]:
    info = root / "meta" / "info.json"
    if not info.is_file():
        raise SystemExit(
            f"--dataset {root}: no LeRobotDataset there (meta/info.json missing); record it with "
            f"`{record}`"
        )
    feats = json.loads(info.read_text())["features"]
    return {k: list(v["shape"]) for k, v in feats.items()}


def check_features(name: str, bench: str, root: Path) -> None:
    """Stop before training when the dataset lacks a feature the benchmark's members are built
    for."""
    have = dataset_features(root, BENCHMARKS[bench].record)
    want = BENCHMARKS[bench].features
    wrong = {k: (shape, have.get(k)) for k, shape in want.items() if have.get(k) != shape}
    if wrong:
        detail = "; ".join(f"{k}: wants {w}, dataset has {h}" for k, (w, h) in wrong.items())
        raise SystemExit(
            f"--dataset {root} does not fit zoo member {name!r} on {bench} ({detail}); record "
            f"the zoo's {bench} dataset with `{BENCHMARKS[bench].record}` or pick --benchmark"
        )


def run_dir(name: str, seed: int, runs: Path = RUNS, init_from: Path | None = None) -> Path:
    """The run folder: ``NAME_seedS``, or ``NAME_seedS_continued`` for a stage that starts from an
    exported checkpoint's weights (so it neither resumes nor overwrites the first stage's run)."""
    return runs / (f"{name}_seed{seed}" + ("_continued" if init_from is not None else ""))


# the flags that size a learning-rate schedule to a run's steps: a continued stage decays over its
# own steps (its optimizer and schedule start afresh)
DECAY_FLAGS = ("--policy.scheduler_decay_steps=", "--scheduler.num_decay_steps=")


def stage_flags(flags: tuple[str, ...], steps: int) -> list[str]:
    """A member's flags with its schedule's decay sized to ``steps``."""
    return [next((f"{d}{steps}" for d in DECAY_FLAGS if f.startswith(d)), f) for f in flags]


def check_init_from(name: str, member: Member, init_from: Path) -> None:
    """Refuse, before any work, a starting checkpoint that is missing or of another class."""
    cfg = init_from / "config.json"
    if not cfg.is_file() or not (init_from / "model.safetensors").is_file():
        raise SystemExit(
            f"--init-from {init_from} holds no exported checkpoint (config.json and "
            f"model.safetensors); export one first: python -m training.zoo export {name}"
        )
    kind = json.loads(cfg.read_text()).get("type")
    if kind != member.policy_type:
        raise SystemExit(
            f"--init-from {init_from} is a {kind!r} checkpoint; zoo member {name!r} is "
            f"{member.policy_type!r}: pass a checkpoint of that member"
        )


def last_checkpoint(out: Path) -> Path | None:
    last = out / "checkpoints" / "last"
    return last if (last / "pretrained_model" / "config.json").is_file() else None


def lerobot_train() -> str:
    """lerobot's trainer beside this interpreter (a venv), else the one on PATH (a
    ``pip install --target`` folder's ``bin``)."""
    beside = Path(sys.executable).with_name("lerobot-train")
    if beside.is_file():
        return str(beside)
    found = shutil.which("lerobot-train")
    if found is None:
        raise SystemExit(
            "lerobot-train is neither beside this Python nor on PATH: install lerobot "
            "(`make setup`), or put the folder holding lerobot-train on PATH"
        )
    return found


def train_command(name: str, member: Member, args: argparse.Namespace) -> list[str]:
    out = run_dir(name, args.seed, args.runs, args.init_from)
    exe = lerobot_train()
    last = last_checkpoint(out)
    steps = args.steps or member.steps
    if last is not None:
        # lerobot resumes from the saved train config (policy, optimizer, step, data order)
        return [
            exe,
            f"--config_path={last / 'pretrained_model' / 'train_config.json'}",
            "--resume=true",
            f"--steps={steps}",
            f"--save_freq={args.save_freq or member.save_freq}",
        ]
    if args.init_from is not None:
        # lerobot-train's fine-tuning path: config and weights from the folder, the flags
        # override its config, the optimizer and schedule start afresh over this stage's steps
        policy = [f"--policy.path={args.init_from}"]
        flags = stage_flags(member.flags, steps)
    else:
        policy = [f"--policy.type={member.policy_type}"]
        flags = list(member.flags)
    return [
        exe,
        f"--dataset.repo_id=local/zoo_{args.benchmark}",
        f"--dataset.root={args.dataset}",
        *policy,
        f"--policy.device={args.device}",
        "--policy.push_to_hub=false",
        *flags,
        *member.benchmark_flags.get(args.benchmark, ()),
        # a continued stage keeps its checkpoint's vocabulary (its word embeddings are sized to it)
        *([vocab_flag(args.dataset)] if member.vocab and args.init_from is None else []),
        f"--output_dir={out}",
        f"--job_name=zoo_{args.benchmark}_{name}",
        f"--seed={args.seed}",
        f"--steps={steps}",
        f"--batch_size={member.batch_size}",
        f"--save_freq={args.save_freq or member.save_freq}",
        "--log_freq=100",
        f"--num_workers={args.num_workers}",
        "--wandb.enable=false",
    ]


def device_name(device: str) -> str:
    """The accelerator a session trained on, by name (``cpu`` where none)."""
    if not device.startswith("cuda"):
        return device
    import torch

    return torch.cuda.get_device_name(torch.device(device)) if torch.cuda.is_available() else device


def cmd_train(args: argparse.Namespace) -> None:
    from training.zoo_eval_launch import (
        EvaluatorProcess,
        check_train_flags,
        children_cpu_s,
        wait_training,
    )

    member = _member(args.name)
    check_features(args.name, args.benchmark, args.dataset)
    if args.init_from is not None:
        check_init_from(args.name, member, args.init_from)
    if args.eval_every is not None:
        check_train_flags(args, args.save_freq or member.save_freq)
    out = run_dir(args.name, args.seed, args.runs, args.init_from)
    install()  # the sub-model files the member names by hub id (no-op when present)
    cmd = train_command(args.name, member, args)
    print(" ".join(cmd), flush=True)
    from workers.hardware import cpu_model

    t0, cpu0 = time.perf_counter(), children_cpu_s()
    child = subprocess.Popen(cmd, cwd=ROOT, env=offline_env(args.threads))
    # evaluates the checkpoints as they are saved, in a process of its own (training never waits)
    evaluator = EvaluatorProcess.for_training(args, out) if args.eval_every else None

    # a stop (SIGTERM / SIGINT) goes to lerobot-train (and the evaluator), and the session is
    # still logged: its last checkpoint is where the next `train` resumes
    def stop(signum: int, _frame: object) -> None:
        child.send_signal(signum)
        if evaluator is not None:
            evaluator.stop(signum)

    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, stop)
    try:
        rc = wait_training(child, args.time_limit_s, evaluator)
    except subprocess.TimeoutExpired:
        # the session's time is up: the last saved checkpoint stays, and is where `train` resumes
        # (TERM, not INT: lerobot-train went on for a minute after an INT on a CUDA machine)
        print(f"--time-limit-s {args.time_limit_s:g} reached: stopping lerobot-train", flush=True)
        child.terminate()
        try:
            rc = child.wait(timeout=30)
        except subprocess.TimeoutExpired:
            child.kill()
            rc = child.wait()
    seconds = round(time.perf_counter() - t0, 1)
    # lerobot-train's own CPU (an evaluator reaped meanwhile is not training's)
    train_cpu_s = children_cpu_s() - cpu0 - (evaluator.reaped_cpu_s if evaluator else 0.0)
    # wall time accumulates over resumed sessions (the model card states the total); recorded
    # when training ends, so the checkpoint exports while the evaluator finishes its last steps
    log = out / "zoo_sessions.jsonl"
    if out.exists():
        with log.open("a") as f:
            f.write(
                json.dumps(
                    {
                        "seconds": seconds,
                        "rc": rc,
                        "train_cpu_s": round(train_cpu_s, 1),
                        "cpu": cpu_model(),
                        "device": device_name(args.device),
                        "threads": args.threads,
                        "command": cmd,
                    }
                )
                + "\n"
            )
    if evaluator is not None:
        evaluator.finish(args.eval_final_wait_s)
    raise SystemExit(rc)


def cmd_export(args: argparse.Namespace) -> None:
    member = _member(args.name)
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


def cmd_list(args: argparse.Namespace) -> None:
    bench = BENCHMARKS[args.benchmark]
    for name, m in MEMBERS.items():
        last = last_checkpoint(run_dir(name, 0, bench.runs))
        state = "not trained"
        if last is not None:
            step = json.loads((last / "training_state" / "training_step.json").read_text())
            state = f"step {step['step']} of {m.steps}"
        shipped = "shipped" if (bench.shipped / name / "config.json").is_file() else "not shipped"
        print(f"{name:10s} {m.policy_type:10s} {state:22s} {shipped}")


def _member(name: str) -> Member:
    if name not in MEMBERS:
        import difflib

        close = difflib.get_close_matches(name, MEMBERS, n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise SystemExit(f"unknown zoo member {name!r}{hint}; members: {sorted(MEMBERS)}")
    return MEMBERS[name]


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="verb", required=True)
    t = sub.add_parser("train", help="train (or resume) one member with lerobot-train")
    t.add_argument("name")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--steps", type=int, default=None, help="override the member's steps")
    t.add_argument(
        "--save-freq",
        type=int,
        default=None,
        help="override the member's checkpoint interval (a session that ends soon)",
    )
    t.add_argument("--dataset", type=Path, default=None, help="default: the benchmark's")
    t.add_argument("--device", default="cpu")
    t.add_argument("--threads", type=int, default=2)
    t.add_argument("--num-workers", type=int, default=0)
    t.add_argument("--runs", type=Path, default=None, help="where lerobot-train's runs go")
    t.add_argument(
        "--time-limit-s",
        type=float,
        default=None,
        help="stop lerobot-train after this many seconds (its last checkpoint is kept; "
        "`train` again resumes from it)",
    )
    from training.zoo_eval_launch import add_train_flags

    add_train_flags(t)
    t.set_defaults(func=cmd_train)
    e = sub.add_parser("export", help="copy the last checkpoint to checkpoints/zoo/[BENCH/]NAME")
    e.add_argument("name")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--dest", type=Path, default=None)
    e.add_argument("--runs", type=Path, default=None)
    e.add_argument("--dataset", type=Path, default=None)
    e.set_defaults(func=cmd_export)
    ls = sub.add_parser("list", help="members and their state")
    ls.set_defaults(func=cmd_list)
    for p in (t, e, ls):
        p.add_argument("--benchmark", choices=sorted(BENCHMARKS), default="tabletop")
    for p in (t, e):
        p.add_argument(
            "--init-from",
            type=Path,
            default=None,
            help="an exported checkpoint whose weights this stage starts from (lerobot-train's "
            "--policy.path); its run folder is NAME_seedS_continued",
        )
    args = ap.parse_args(argv)
    os.chdir(ROOT)
    bench = BENCHMARKS[args.benchmark]
    if getattr(args, "dataset", "-") is None:
        args.dataset = bench.dataset
    if getattr(args, "runs", "-") is None:
        args.runs = bench.runs
    args.func(args)


if __name__ == "__main__":
    main()
