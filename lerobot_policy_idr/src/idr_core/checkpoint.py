"""Checks of a lerobot checkpoint folder made before any weight is loaded or any robot moves:
it exists, holds a config.json of a policy type and a complete safetensors file (pickled
weights are never opened). Shared by the idr policy (its base) and idr-eval's lerobot backbone.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

PICKLE_WEIGHTS = ("pytorch_model.bin", "model.bin", "model.pt", "model.pth", "model.ckpt")
WEIGHTS = "model.safetensors"


def check_checkpoint_dir(path: str | Path, field: str, known_types: set[str] | None = None) -> dict:
    """Refuse a folder that is not a loadable lerobot checkpoint, naming ``field`` (the
    setting that gave the path); returns its config.json as a dict."""
    p = Path(path).expanduser()
    if not p.is_dir():
        raise ValueError(f"{field}={str(path)!r} does not exist (a checkpoint folder)")
    if not (p / "config.json").is_file():
        raise ValueError(f"{field}={str(path)!r} is not a lerobot policy: no config.json in it")
    try:
        cfg = json.loads((p / "config.json").read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"{field}={str(path)!r}: config.json is not JSON ({e})") from None
    if not isinstance(cfg, dict):
        raise ValueError(
            f"{field}={str(path)!r}: config.json holds a {type(cfg).__name__}, not an "
            "object with the policy's config"
        )
    if "type" not in cfg:
        raise ValueError(f"{field}={str(path)!r}: config.json has no policy 'type'")
    if known_types and cfg["type"] not in known_types:
        raise ValueError(
            f"{field}={str(path)!r}: policy type {cfg['type']!r} is not one lerobot "
            f"knows; known: {sorted(known_types)}"
        )
    weights = p / WEIGHTS
    if not weights.is_file():
        pickles = [f for f in PICKLE_WEIGHTS if (p / f).exists()]
        hint = (
            f" (found {pickles}: pickled weights are refused, convert them to safetensors)"
            if pickles
            else ""
        )
        raise ValueError(f"{field}={str(path)!r} has no {WEIGHTS}{hint}")
    check_safetensors(weights, f"{field}={str(path)!r}")
    return cfg


def check_safetensors(weights: Path, what: str) -> None:
    """The header parses and covers the file exactly (a truncated copy, or a pickle renamed
    to model.safetensors, fails here); tensors are not read."""
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(weights), framework="numpy") as f:
            n = len(list(f.keys()))
    except (SafetensorError, OSError) as e:
        raise ValueError(
            f"{what}: {WEIGHTS} is not a complete safetensors file ({e}); a truncated copy or "
            "another format (pickles are never loaded)"
        ) from None
    if n == 0:
        raise ValueError(f"{what}: {WEIGHTS} holds no tensors")


def sha256_file(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()
