"""What a run's results depend on beyond its config: the checkpoint's content and the code.

A resume must not mix results of two checkpoints saved at the same path, nor (unless the user
says so) of two versions of the code. ``run.json`` records both; :func:`check_resume` compares
them before any work. The checkpoint's digest is the sha256 of every file in its folder
(relative names and contents), recorded with each file's size and mtime: a resume whose files
have the same size and mtime reuses the recorded digest without reading them again (a pi0.5
checkpoint is ~8 GB: hashing it takes tens of seconds once, per run dir).
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from pipeline.planning.config import ConfigError, RunConfig

CHUNK = 1 << 20


def checkpoint_path(cfg: RunConfig) -> Path | None:
    """The local checkpoint a backbone loads (``backbone.params.path``), if any."""
    path = cfg.backbone.params.get("path")
    if not isinstance(path, str):
        return None
    p = Path(path).expanduser()
    return p if p.exists() else None


def _files(root: Path) -> list[Path]:
    return sorted(p for p in ([root] if root.is_file() else root.rglob("*")) if p.is_file())


def _stat(root: Path, files: list[Path]) -> dict[str, list[int]]:
    base = root.parent if root.is_file() else root
    return {str(f.relative_to(base)): [f.stat().st_size, f.stat().st_mtime_ns] for f in files}


def checkpoint_record(root: Path, previous: dict[str, Any] | None = None) -> dict[str, Any]:
    """{"path", "sha256", "files": {name: [size, mtime_ns]}}; reuses ``previous``'s digest
    when no file changed size or mtime."""
    files = _files(root)
    stat = _stat(root, files)
    if previous and previous.get("files") == stat and previous.get("sha256"):
        return {"path": str(root.resolve()), "sha256": previous["sha256"], "files": stat}
    h = hashlib.sha256()
    base = root.parent if root.is_file() else root
    for f in files:
        h.update(str(f.relative_to(base)).encode() + b"\0")
        with open(f, "rb") as fh:
            while block := fh.read(CHUNK):
                h.update(block)
    return {"path": str(root.resolve()), "sha256": h.hexdigest(), "files": stat}


def check_resume(
    meta: dict[str, Any],
    checkpoint: dict[str, Any] | None,
    code: str,
    run_dir: Path,
    allow_code_change: bool = False,
) -> None:
    """Refuse resuming ``run_dir`` (its run.json ``meta``) with another checkpoint content, or
    with another code version unless ``allow_code_change``. Run dirs from before these were
    recorded are resumed as before."""
    old = meta.get("checkpoint")
    if old and checkpoint and old.get("sha256") != checkpoint["sha256"]:
        raise ConfigError(
            f"{run_dir} was run with another content of the checkpoint {checkpoint['path']} "
            f"(sha256 {old['sha256'][:12]} then, {checkpoint['sha256'][:12]} now); results of two "
            "checkpoints are never mixed: use a new --out"
        )
    was = meta.get("code_version")
    if was and was != code and not allow_code_change:
        raise ConfigError(
            f"{run_dir} was run with code version {was}, this is {code}; results of two code "
            "versions are not mixed by default: use a new --out, or pass --allow-code-change "
            "if the change cannot affect results"
        )


def check_hardware(
    meta: dict[str, Any], hardware: str | None, run_dir: Path, allow_numerics_change: bool = False
) -> str | None:
    """Refuse resuming ``run_dir`` on another hardware class (workers.hardware) unless
    ``allow_numerics_change``: the same numerical path gives other floats on another CPU model
    or instruction set. A run dir made before the class was recorded: a warning (returned), and
    the resume goes on. ``hardware`` None (a cluster's actors, not this driver, compute): not
    checked here; the episodes' ``hardware`` column and the report name what ran."""
    was = meta.get("hardware_class")
    if hardware is None:
        return None
    if not was:
        return (
            f"{run_dir} was made before the hardware was recorded: its episodes' hardware is "
            f"unknown; resuming on {hardware!r} (the report lists the classes by episode)"
        )
    if was != hardware and not allow_numerics_change:
        raise ConfigError(
            f"{run_dir} was run on {was!r}, this machine is {hardware!r}: the same numerical "
            "path gives other floats on another CPU model or instruction set, so its remaining "
            "episodes would not match the first ones. Resume it on the same hardware, use a "
            "new --out, or pass --allow-numerics-change (the report then says mixed)"
        )
    return None


def check_numerics(
    meta: dict[str, Any], numerics: str, run_dir: Path, allow_numerics_change: bool = False
) -> None:
    """Refuse resuming ``run_dir`` on another numerical path (workers.policy.forward_shape) unless
    ``allow_numerics_change``: its episodes would differ from the first ones in float rounding,
    which in closed loop grows into other trajectories. Run dirs from before it was recorded are
    resumed as before; a mixed run's report names its paths (from the episodes' column)."""
    was = meta.get("numerics")
    if was and was != numerics and not allow_numerics_change:
        raise ConfigError(
            f"{run_dir} was run on the numerical path {was!r}, this config gives {numerics!r} "
            "(executor.policy / batching / forward_rows / torch_threads): its episodes would "
            "differ in float rounding. Use the same executor settings, a new --out, or pass "
            "--allow-numerics-change (the report then names both paths)"
        )
