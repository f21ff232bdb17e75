"""Where a run may write: ``..`` and symlinks must not lead a RUN_DIR out of the output root.

The output root (config ``output_root``) is the trust boundary for paths that come from a
config or are built by scripts: ``name`` is one path component (pipeline.config), and a
RUN_DIR whose ``..`` parts or symlinks resolve outside the output root is refused. A plain
path elsewhere (``--out /scratch/run``, no ``..``, no symlink) is the user's explicit choice
and is allowed.
"""

from __future__ import annotations

import os
from pathlib import Path

from pipeline.config import ConfigError


def _inside(path: Path, root: Path) -> bool:
    return path == root or root in path.parents


def _symlinks(path: Path) -> list[Path]:
    """The symlinks among the components of ``path`` as written (made absolute, not resolved)."""
    absolute = Path(os.path.join(os.getcwd(), path))  # keeps '..' and links as written
    found = []
    current = Path(absolute.anchor)
    for part in absolute.parts[1:]:
        current = current / part
        if part != ".." and current.is_symlink():
            found.append(current)
    return found


def check_writable_dir(run_dir: Path) -> None:
    """A RUN_DIR must be a directory (or not exist yet) whose nearest existing ancestor this
    process can create folders in: refused otherwise, before anything is written."""
    if run_dir.exists() and not run_dir.is_dir():
        raise ConfigError(
            f"RUN_DIR {str(run_dir)!r} is an existing file, not a directory; choose another --out"
        )
    probe = run_dir
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir():
        raise ConfigError(f"RUN_DIR {str(run_dir)!r}: {probe} is a file, not a directory")
    target = run_dir if run_dir.exists() else probe
    if not os.access(target, os.W_OK | os.X_OK) or str(target.resolve()).startswith(
        ("/proc", "/sys")
    ):
        raise ConfigError(
            f"RUN_DIR {str(run_dir)!r}: {target} is not writable by this user; choose an --out "
            "you can write to"
        )


def check_run_dir(run_dir: str | Path, output_root: str | Path) -> Path:
    """Return ``run_dir``, or raise ConfigError if ``..`` or a symlink takes it outside
    ``output_root``, or it cannot be written (a file, a read-only or virtual filesystem)."""
    given = Path(run_dir).expanduser()
    check_writable_dir(given)
    root = Path(output_root).expanduser().resolve()
    resolved = given.resolve()
    if _inside(resolved, root):
        return given
    if ".." in given.parts:
        raise ConfigError(
            f"RUN_DIR {str(run_dir)!r}: its '..' leads to {resolved}, outside the output root "
            f"{root} (output_root); give a path without '..', or set output_root"
        )
    links = _symlinks(given)
    if links:
        raise ConfigError(
            f"RUN_DIR {str(run_dir)!r}: the symlink {links[0]} -> {links[0].resolve()} leads "
            f"outside the output root {root} (output_root); give the real path {resolved}, or set "
            "output_root to a folder that contains it"
        )
    return given
