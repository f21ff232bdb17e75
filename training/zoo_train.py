"""``python -m training.zoo train``: one member trained (or resumed) by ``lerobot-train`` with
its flags, after the dataset and a starting checkpoint are checked; each session logged in the
run folder (``zoo_sessions.jsonl``: the export's card data)."""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from training.zoo_benchmarks import BENCHMARKS, ROOT, last_checkpoint, offline_env, run_dir
from training.zoo_data import dataset_tasks
from training.zoo_hub import install
from training.zoo_members import Member, member_named, stage_flags


def vocab_flag(root: Path) -> str:
    from training.tiny_vla_demos import vocabulary

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

    member = member_named(args.name)
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
