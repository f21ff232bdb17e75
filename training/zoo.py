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

The members and their flags: ``training/zoo_members.py``; the commands: ``training/zoo_train.py``,
``training/zoo_export.py``; where a benchmark's dataset, runs and checkpoints lie:
``training/zoo_benchmarks.py``.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from training.zoo_benchmarks import BENCHMARKS, ROOT, last_checkpoint, run_dir
from training.zoo_export import cmd_export
from training.zoo_members import MEMBERS
from training.zoo_train import cmd_train


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
