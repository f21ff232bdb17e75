"""Train the tiny VLA on LeRobotDatasets of expert demonstrations; save it in lerobot's format.

The output folder is a regular lerobot checkpoint (``config.json``, ``model.safetensors``,
``policy_preprocessor.json`` / ``policy_postprocessor.json`` with the normalization stats), so
the project's lerobot adapter loads it like any other policy. The whole dataset is held in
memory as uint8 tensors (a few GB at most for the tabletop demos), which makes CPU training
fast; images get a random shift of a few pixels as augmentation.

Reproduce the shipped checkpoint (docs/tiny-vla.md):

    python -m training.train_tiny_vla --data data/tabletop_demos_po data/tabletop_demos_org \
        --out checkpoints/tiny_vla --steps 4000 --batch-size 64 --seed 0
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from idr_core.features import ACTION, OBS_STATE

from training.tiny_vla_demos import DemoTensors, load_demos, vocabulary


def random_shift(x: torch.Tensor, pad: int, gen: torch.Generator) -> torch.Tensor:
    """Shift each image by up to ``pad`` pixels (replicate-padded crop), as in DrQ."""
    if pad == 0:
        return x
    b, _, h, w = x.shape
    padded = F.pad(x, (pad, pad, pad, pad), mode="replicate")
    dx = torch.randint(0, 2 * pad + 1, (b,), generator=gen)
    dy = torch.randint(0, 2 * pad + 1, (b,), generator=gen)
    rows = (dy[:, None] + torch.arange(h)[None])[:, :, None].expand(b, h, w)
    cols = (dx[:, None] + torch.arange(w)[None])[:, None, :].expand(b, h, w)
    bidx = torch.arange(b)[:, None, None].expand(b, h, w)
    return padded.permute(0, 2, 3, 1)[bidx, rows, cols].permute(0, 3, 1, 2)


def _checkpoint_stats(path: Path) -> dict[str, dict[str, torch.Tensor]]:
    """The normalization stats a lerobot checkpoint's preprocessor was saved with."""
    from safetensors.torch import load_file

    files = sorted(Path(path).glob("policy_preprocessor_step_*_normalizer_processor.safetensors"))
    if not files:
        raise FileNotFoundError(
            f"{path}: no policy_preprocessor normalizer stats to fine-tune from"
        )
    stats: dict[str, dict[str, torch.Tensor]] = {}
    for name, value in load_file(str(files[0])).items():
        key, stat = name.rsplit(".", 1)
        stats.setdefault(key, {})[stat] = value
    return stats


# the net's size: TinyVLAConfig fields, chosen for a run from scratch (--cnn-channels, ...)
ARCHITECTURE_FIELDS = ("cnn_channels", "cnn_strides", "text_dim", "hidden_dim")


def train(
    data: list[Path],
    out: Path,
    steps: int,
    batch_size: int = 128,
    chunk: int = 8,
    seed: int = 0,
    lr: float = 1e-3,
    shift: int = 0,
    state_dropout: float = 0.0,
    state_noise: float = 0.0,
    ignored_state_dims: tuple[int, ...] = (),
    log_every: int = 100,
    device: str = "cpu",
    init: Path | None = None,
    architecture: dict | None = None,
) -> dict:
    """``architecture``: TinyVLAConfig fields of the net (``ARCHITECTURE_FIELDS``) for a policy
    trained from scratch; a fine-tune keeps its checkpoint's."""
    architecture = {k: v for k, v in (architecture or {}).items() if v is not None}
    if init is not None and architecture:
        raise ValueError(
            f"--init {init} keeps its own architecture: leave out "
            + ", ".join(f"--{k.replace('_', '-')}" for k in architecture)
        )
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    t0 = time.perf_counter()
    demos = load_demos(data, chunk)
    n = demos.state.shape[0]
    load_s = time.perf_counter() - t0
    print(f"loaded {n} frames from {[str(d) for d in data]} in {load_s:.0f}s", flush=True)

    if init is not None:
        cfg, stats, policy = _fine_tune_start(init, demos, chunk, ignored_state_dims)
    else:
        cfg, stats, policy = _scratch_start(demos, chunk, ignored_state_dims, architecture)
    policy = policy.to(device)
    policy.train()
    settings = _Steps(steps, batch_size, lr, shift, state_dropout, state_noise, log_every)
    losses, t1 = _optimize(policy, cfg, demos, stats, settings, device, gen)
    _save_checkpoint(policy, cfg, stats, out)
    meta = {
        "command": " ".join(["python -m training.train_tiny_vla", *sys.argv[1:]]),
        "frames": n,
        "episodes": demos.n_episodes,
        "steps": steps,
        "batch_size": batch_size,
        "lr": lr,
        "seed": seed,
        "shift": shift,
        "state_dropout": state_dropout,
        "state_noise": state_noise,
        "ignored_state_dims": list(ignored_state_dims),
        "final_loss": float(np.mean(losses[-100:])),
        "params": sum(p.numel() for p in policy.parameters()),
        "load_seconds": load_s,
        "train_seconds": time.perf_counter() - t1,
        "device": device,
        "init": str(init) if init else None,
        "architecture": {
            k: list(v) if isinstance(v, tuple | list) else v
            for k in ARCHITECTURE_FIELDS
            for v in [getattr(cfg, k)]
        },
    }
    (out / "train_meta.json").write_text(json.dumps(meta, indent=2) + "\n")
    return meta


def _fine_tune_start(
    init: Path, demos: DemoTensors, chunk: int, ignored_state_dims: tuple[int, ...]
) -> tuple[Any, dict[str, dict[str, torch.Tensor]], Any]:
    """The config, normalization stats and policy of the ``init`` checkpoint: its
    normalization and vocabulary stay (a policy's inputs and outputs must mean what they meant
    when it was trained)."""
    from lerobot_policy_idr.tiny_vla.configuration_tiny_vla import TinyVLAConfig
    from lerobot_policy_idr.tiny_vla.modeling_tiny_vla import TinyVLAPolicy

    cfg = TinyVLAConfig.from_pretrained(init)
    stats = _checkpoint_stats(init)
    missing = sorted(set(vocabulary(demos.tasks)) - set(cfg.vocab))
    if missing:
        raise ValueError(f"--init {init}: instructions use words it never saw: {missing}")
    if list(cfg.ignored_state_dims) != list(ignored_state_dims):
        print(
            f"--init: keeping its ignored_state_dims {cfg.ignored_state_dims}"
            f" (asked {list(ignored_state_dims)})",
            flush=True,
        )
    if cfg.chunk_size != chunk:
        raise ValueError(f"--init {init} predicts chunks of {cfg.chunk_size}, --chunk {chunk}")
    return cfg, stats, TinyVLAPolicy.from_pretrained(init, config=cfg)


def _scratch_start(
    demos: DemoTensors, chunk: int, ignored_state_dims: tuple[int, ...], architecture: dict
) -> tuple[Any, dict[str, dict[str, torch.Tensor]], Any]:
    """A new policy's config (features, vocabulary and net from the demonstrations and
    ``architecture``), the demonstrations' normalization stats, and the policy."""
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot_policy_idr.tiny_vla.configuration_tiny_vla import TinyVLAConfig
    from lerobot_policy_idr.tiny_vla.modeling_tiny_vla import TinyVLAPolicy

    stats = {
        key: {
            "mean": values.mean(0),
            "std": values.std(0).clamp(min=1e-3),
            "min": values.min(0).values,
            "max": values.max(0).values,
        }
        for key, values in ((OBS_STATE, demos.state), (ACTION, demos.action))
    }
    inputs = {
        k: PolicyFeature(FeatureType.VISUAL, tuple(v.shape[1:])) for k, v in demos.images.items()
    }
    inputs[OBS_STATE] = PolicyFeature(FeatureType.STATE, (demos.state.shape[1],))
    outputs = {ACTION: PolicyFeature(FeatureType.ACTION, (demos.action.shape[1],))}
    cfg = TinyVLAConfig(
        input_features=inputs,
        output_features=outputs,
        vocab=vocabulary(demos.tasks),
        chunk_size=chunk,
        n_action_steps=chunk,
        ignored_state_dims=list(ignored_state_dims),
        device="cpu",
        **architecture,
    )
    cfg.validate_features()  # e.g. one stride per conv layer, before any training
    return cfg, stats, TinyVLAPolicy(cfg)


@dataclass(frozen=True)
class _Steps:
    """How the policy is optimized: ``train``'s arguments of that name."""

    steps: int
    batch_size: int
    lr: float
    shift: int
    state_dropout: float
    state_noise: float
    log_every: int


def _family_weights(tasks: list[str]) -> torch.Tensor:
    """Sampling weights that balance task families (the organize chain has ~5x the frames of a
    pick): each family gets an equal share of every batch."""
    family = np.array([t.split(" ")[0] for t in tasks])
    weights = np.zeros(len(tasks))
    for f in np.unique(family):
        weights[family == f] = 1.0 / (family == f).sum()
    return torch.from_numpy(weights / weights.sum())


def _optimize(
    policy: Any,
    cfg: Any,
    demos: DemoTensors,
    stats: dict[str, dict[str, torch.Tensor]],
    run: _Steps,
    device: str,
    gen: torch.Generator,
) -> tuple[list[float], float]:
    """``run.steps`` optimizer steps on batches drawn from ``demos``; the losses, and when the
    first step started (``time.perf_counter``)."""
    s_mean, s_std = stats[OBS_STATE]["mean"], stats[OBS_STATE]["std"]
    a_mean, a_std = stats[ACTION]["mean"], stats[ACTION]["std"]
    opt = torch.optim.AdamW(policy.parameters(), lr=run.lr, weight_decay=cfg.optimizer_weight_decay)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=run.steps, eta_min=run.lr * 0.05)
    # the whole dataset lives on the training device (uint8 images: ~55 KB a frame, two cameras)
    images = {k: v.to(device) for k, v in demos.images.items()}
    state_n = ((demos.state - s_mean) / s_std).to(device)
    action_n = ((demos.action - a_mean) / a_std).to(device)
    chunk_index, chunk_pad = demos.chunk_index.to(device), demos.chunk_pad.to(device)
    tasks = np.array(demos.tasks, dtype=object)
    weights = _family_weights(demos.tasks)
    losses = []
    t1 = time.perf_counter()
    for step in range(1, run.steps + 1):
        idx = torch.multinomial(weights, run.batch_size, replacement=True, generator=gen)
        didx = idx.to(device)
        batch = {
            k: random_shift(v[didx].float() / 255.0, run.shift, gen) for k, v in images.items()
        }
        batch[OBS_STATE] = _perturbed_state(state_n[didx], run, device, gen)
        batch[ACTION] = action_n[chunk_index[didx]]
        batch["action_is_pad"] = chunk_pad[didx]
        batch["task"] = list(tasks[idx.numpy()])
        loss, _ = policy(batch)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
        opt.step()
        sched.step()
        losses.append(float(loss.detach()))
        if step % run.log_every == 0 or step == run.steps:
            print(
                f"step {step}/{run.steps} loss {np.mean(losses[-run.log_every :]):.4f} "
                f"({(time.perf_counter() - t1) / step * 1e3:.0f} ms/step)",
                flush=True,
            )
    return losses, t1


def _perturbed_state(
    state: torch.Tensor, run: _Steps, device: str, gen: torch.Generator
) -> torch.Tensor:
    """A batch's normalized state with ``run``'s dropout and noise applied."""
    if run.state_dropout:
        # zero (= the dataset mean) the state of some samples, so that the policy must find
        # the cubes in the images instead of replaying a state-indexed average trajectory
        keep = torch.rand(run.batch_size, 1, generator=gen) >= run.state_dropout
        state = state * keep.to(device)
    if run.state_noise:
        # Gaussian noise on the normalized state: the end-effector orientation varies by a
        # few thousandths of a radian with the commanded motion, so a net fed the exact
        # state learns to copy its previous action from that tilt (the "copycat" shortcut)
        # and drifts off in closed loop; noise drowns that signal, keeps positions usable
        state = state + run.state_noise * torch.randn(state.shape, generator=gen).to(device)
    return state


def _save_checkpoint(
    policy: Any, cfg: Any, stats: dict[str, dict[str, torch.Tensor]], out: Path
) -> None:
    """The policy (on CPU) and its processors with ``stats``, in lerobot's format."""
    from lerobot.processor.factory import make_default_pre_post_processors

    policy.eval().to("cpu")
    out.mkdir(parents=True, exist_ok=True)
    policy.save_pretrained(out)
    pre, post = make_default_pre_post_processors(cfg, dataset_stats=stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, nargs="+", required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch-size", type=int, default=128)
    ap.add_argument("--chunk", type=int, default=8)
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--shift",
        type=int,
        default=0,
        help="random-shift augmentation in pixels (0: off;"
        " the agent view is a fixed camera, so absolute image positions locate the cubes)",
    )
    ap.add_argument(
        "--state-dropout",
        type=float,
        default=0.0,
        help="share of samples trained with the state zeroed",
    )
    ap.add_argument(
        "--state-noise",
        type=float,
        default=0.1,
        help="std of Gaussian noise added to the normalized state in training",
    )
    ap.add_argument(
        "--ignored-state-dims",
        type=int,
        nargs="*",
        default=[3, 4, 5],
        help="state dims the net does not read (default: the tabletop's eef orientation)",
    )
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument(
        "--cnn-channels", type=int, nargs="+", default=None, help="from scratch: 16 32 64"
    )
    ap.add_argument(
        "--cnn-strides",
        type=int,
        nargs="+",
        default=None,
        help="from scratch: one per layer, 2 2 2 (2 2 1: a 24 x 24 keypoint map at 96 px)",
    )
    ap.add_argument("--text-dim", type=int, default=None, help="from scratch: 64")
    ap.add_argument("--hidden-dim", type=int, default=None, help="from scratch: 256")
    ap.add_argument(
        "--init",
        type=Path,
        default=None,
        help="fine-tune this tiny_vla checkpoint (keeps its normalization stats and vocabulary)",
    )
    ap.add_argument(
        "--device",
        default="cpu",
        help="where to train (cpu, cuda); the saved checkpoint is for CPU either way",
    )
    return ap


def main() -> None:
    args = _parser().parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    meta = train(
        args.data,
        args.out,
        args.steps,
        args.batch_size,
        args.chunk,
        args.seed,
        args.lr,
        args.shift,
        args.state_dropout,
        args.state_noise,
        tuple(args.ignored_state_dims),
        device=args.device,
        init=args.init,
        architecture={
            k: tuple(v) if isinstance(v, list) else v
            for k in ARCHITECTURE_FIELDS
            for v in [getattr(args, k)]
        },
    )
    print(json.dumps(meta, indent=2))


if __name__ == "__main__":
    main()
