"""A run directory: every name inside it, its one ``run.json``, whole-or-nothing writes, and
where a run may write.

Layout of ``RUN_DIR`` (the contract of docs/guarantees.md):

- ``config.yaml`` the resolved config; ``run.json`` the run's identity (run id, config
  fingerprint, code version, checkpoint digest, env server, checkpoint fit, protocol,
  quarantined files): written and read only through :func:`read_run_json` / :func:`write_run_json`
- ``episodes/``, ``steps/`` Parquet batches (pipeline.results.store), ``quarantine/`` unreadable
  batches moved aside
- ``calibration_episodes/{episodes,steps}/`` the held-out episodes that fit tau (a
  ``calibration:`` block): a store of their own, in no table, comparison or metric of the run
- ``report.md``, ``report.html``, ``figures/``, ``calibration.json``, ``tracking.json``,
  ``logs/``, ``.lock``
- ``policy.token`` the run's secret for its policy sockets (a shared policy on the socket
  transport): mode 0600, made with the run, kept for its resumes; never logged, never tracked

Where a run may write: ``..`` and symlinks must not lead a RUN_DIR out of the output root.
The output root (config ``output_root``) is the trust boundary for paths that come from a
config or are built by scripts: ``name`` is one path component (pipeline.planning.config), and
a RUN_DIR whose ``..`` parts or symlinks resolve outside the output root is refused. A plain
path elsewhere (``--out /scratch/run``, no ``..``, no symlink) is the user's explicit choice
and is allowed.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError

RUN_JSON = "run.json"
CONFIG_YAML = "config.yaml"
REPORT_MD = "report.md"
REPORT_HTML = "report.html"
EPISODES_DIR = "episodes"
STEPS_DIR = "steps"
QUARANTINE_DIR = "quarantine"
FIGURES_DIR = "figures"  # RUN_DIR/figures/<name>.png
VIDEOS_DIR = "videos"  # RUN_DIR/videos/cell=<id>/<task>/episode_<i>.mp4 (videos.episodes)
CALIBRATION_FILE = "calibration.json"
HELD_OUT_DIR = "calibration_episodes"  # RUN_DIR/calibration_episodes/{episodes,steps}/cell=*/
TRACKING_FILE = "tracking.json"
LOGS_DIR = "logs"
LOCK_FILE = ".lock"
POLICY_TOKEN_FILE = "policy.token"  # hex, mode 0600 (workers.policy.socket_settings.SocketToken)
MARKERS = (RUN_JSON, EPISODES_DIR, STEPS_DIR)  # any of them: the folder is an idr-eval run dir


def write_atomic(path: Path, write: Callable[[Path], object], *, fsync: bool = False) -> Path:
    """Whole or not at all: ``write(tmp)`` fills a temporary sibling that is renamed over
    ``path``; a crash or a full disk leaves the old file (or none), never a truncated one.
    ``fsync``: the bytes and the rename survive a power cut too (the Parquet batches)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")  # hidden: dataset scans skip it
    try:
        write(tmp)
        if fsync:
            with open(tmp, "rb") as f:
                os.fsync(f.fileno())
        os.replace(tmp, path)
        if fsync:
            dir_fd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dir_fd)
            finally:
                os.close(dir_fd)
    finally:
        tmp.unlink(missing_ok=True)
    return path


def write_text_atomic(path: Path, text: str) -> Path:
    """:func:`write_atomic` for text."""
    return write_atomic(path, lambda tmp: tmp.write_text(text))


def read_run_json(run_dir: str | Path) -> dict[str, Any] | None:
    """``run.json`` of a run dir, or None when it has none (a new dir, or one whose run.json
    was lost: ``idr-eval run --adopt``)."""
    path = Path(run_dir) / RUN_JSON
    return json.loads(path.read_text()) if path.is_file() else None


def write_run_json(run_dir: str | Path, meta: dict[str, Any]) -> None:
    """Replace ``run.json`` whole."""
    write_text_atomic(Path(run_dir) / RUN_JSON, json.dumps(meta, indent=2))


def update_run_json(run_dir: str | Path, **changes: Any) -> dict[str, Any]:
    """Read, change the given keys, write back whole; returns the new record."""
    meta = read_run_json(run_dir) or {}
    meta.update(changes)
    write_run_json(run_dir, meta)
    return meta


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


def policy_token(run_dir: str | Path) -> bytes:
    """The run's policy-socket secret (32 bytes), from ``RUN_DIR/policy.token``: made on first
    use with mode 0600 (created so, never widened), and made anew where the file is unreadable
    or others may read it (a token others could read is no secret)."""
    import secrets

    path = Path(run_dir) / POLICY_TOKEN_FILE
    try:
        st = path.stat()
        if st.st_mode & 0o077 == 0:
            secret = bytes.fromhex(path.read_text().strip())
            if len(secret) == 32:
                return secret
    except (OSError, ValueError):
        pass
    secret = secrets.token_bytes(32)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(secret.hex() + "\n")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return secret
