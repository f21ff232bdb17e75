"""A zoo checkpoint carried off a machine through a channel with a size limit per file.

ACT's and Diffusion's checkpoints (two ResNet-18s, 50-70 MB in float32) are trained where a GPU
is and evaluated here; the channel between the two carries a few files of at most 16 MiB. So
``pack`` stores the weights at float16 (half the bytes), tars the checkpoint folder and splits
the tar into parts; ``unpack`` joins them and writes the weights back as float32, the dtype
lerobot's factory builds the model in. The rounding is measured where the float32 weights still
exist: ``pack --dataset`` runs both checkpoints open-loop on the same frames with the same noise
(``training/zoo_openloop.py``) and writes the largest action difference, in the dataset's
standard deviations, to ``carry.json``; ``unpack`` copies it into ``train_meta.json``.

    python -m training.zoo_carry pack CHECKPOINT --out DIR [--dataset DATASET]
    python -m training.zoo_carry unpack DIR/NAME.tar.part* --dest CHECKPOINT
"""

from __future__ import annotations

import argparse
import json
import shutil
import tarfile
import tempfile
from pathlib import Path

WEIGHTS = "model.safetensors"
CARRY = "carry.json"
PART_BYTES = 15 * 2**20


def _cast(src: Path, dst: Path, dtype: str) -> None:
    """The safetensors file with every float32 (or float16) tensor cast to ``dtype``."""
    import torch
    from safetensors import safe_open
    from safetensors.torch import save_file

    to = getattr(torch, dtype)
    with safe_open(str(src), "pt") as f:
        meta = f.metadata()
        tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 (safe_open has no iter)
    floats = (torch.float32, torch.float16)
    out = {k: (v.to(to) if v.dtype in floats else v).contiguous() for k, v in tensors.items()}
    save_file(out, str(dst), metadata=meta)


def pack(checkpoint: Path, out: Path, dataset: Path | None, frames: int = 100) -> list[Path]:
    name = checkpoint.name
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        half = Path(tmp) / name
        shutil.copytree(checkpoint, half)
        _cast(checkpoint / WEIGHTS, half / WEIGHTS, "float16")
        carry: dict = {"weights_dtype": "float16", "source_dtype": "float32"}
        if dataset is not None:
            carry.update(rounding(checkpoint, half, dataset, frames))
        (half / CARRY).write_text(json.dumps(carry, indent=2) + "\n")
        tar = Path(tmp) / f"{name}.tar"
        with tarfile.open(tar, "w") as t:
            t.add(half, arcname=name)
        data = tar.read_bytes()
    parts = []
    for i in range(0, len(data), PART_BYTES):
        part = out / f"{name}.tar.part{i // PART_BYTES:02d}"
        part.write_bytes(data[i : i + PART_BYTES])
        parts.append(part)
    return parts


def rounding(full: Path, half: Path, dataset: Path, frames: int) -> dict:
    """The float16 checkpoint against the float32 one, open-loop on the same frames and noise."""
    import numpy as np

    from training.zoo_openloop import open_loop_error

    a = open_loop_error(full, dataset, frames, keep_actions=True)
    b = open_loop_error(half, dataset, frames, keep_actions=True)
    diff = np.abs(np.asarray(a.pop("actions_in_std")) - np.asarray(b.pop("actions_in_std")))
    return {
        "frames": a["frames"],
        "max_abs_action_diff_in_std": float(diff.max()),
        "mean_abs_action_diff_in_std": float(diff.mean()),
        "open_loop_float32": a["mae_in_std"],
        "open_loop_float16": b["mae_in_std"],
    }


def unpack(parts: list[Path], dest: Path) -> Path:
    parts = sorted(parts)
    with tempfile.TemporaryDirectory() as tmp:
        tar = Path(tmp) / "checkpoint.tar"
        with tar.open("wb") as f:
            for p in parts:
                f.write(p.read_bytes())
        with tarfile.open(tar) as t:
            t.extractall(tmp, filter="data")
        folders = [p for p in Path(tmp).iterdir() if p.is_dir()]
        if len(folders) != 1:
            raise SystemExit(f"{parts[0]}: expected one checkpoint folder in the tar")
        src = folders[0]
        carry = json.loads((src / CARRY).read_text())
        if dest.exists():
            shutil.rmtree(dest)
        shutil.copytree(src, dest)
        _cast(src / WEIGHTS, dest / WEIGHTS, "float32")
    (dest / CARRY).unlink()
    meta_path = dest / "train_meta.json"
    if meta_path.is_file():
        meta = json.loads(meta_path.read_text())
        meta["carried"] = carry
        meta_path.write_text(json.dumps(meta, indent=2) + "\n")
    return dest


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="verb", required=True)
    p = sub.add_parser("pack")
    p.add_argument("checkpoint", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--dataset", type=Path, default=None)
    p.add_argument("--frames", type=int, default=100)
    u = sub.add_parser("unpack")
    u.add_argument("parts", type=Path, nargs="+")
    u.add_argument("--dest", type=Path, required=True)
    args = ap.parse_args(argv)
    if args.verb == "pack":
        for part in pack(args.checkpoint, args.out, args.dataset, args.frames):
            print(part)
    else:
        print(unpack(args.parts, args.dest))


if __name__ == "__main__":
    main()
