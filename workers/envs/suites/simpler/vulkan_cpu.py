"""Vulkan for SAPIEN 2 without a GPU: Mesa's lavapipe from a private prefix plus our layer.

``make setup-simpler`` (scripts/setup_simpler.sh) unpacks Debian bookworm-backports' Mesa
25.0.7 Vulkan drivers, its libdrm and the Vulkan loader into ``.vulkan-cpu/`` (no system
package changes: bookworm's own lavapipe, Mesa 22.3, is refused by SAPIEN) and compiles
``scripts/vulkan_cpu/semaphore_fd_layer.c`` (SAPIEN asks for VK_KHR_external_semaphore_fd,
which lavapipe lacks; the layer lists it and drops it at device creation). ``configure`` makes
this process use them: it must run before SAPIEN is imported, and needs no LD_LIBRARY_PATH
(the newer libdrm and the loader are loaded by path first, so the driver links to them).
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

PREFIX = Path(__file__).resolve().parents[4] / ".vulkan-cpu"
LAYER = "VK_LAYER_IDR_semaphore_fd"
RENDERERS = ("auto", "gpu", "lavapipe")
GPU_ICDS = ("nvidia_icd.json", "nvidia_icd.x86_64.json", "radeon_icd.x86_64.json")
SETUP_HINT = "make setup-simpler builds .vulkan-cpu (lavapipe + the layer)"


def prefix(path: str | None = None) -> Path:
    return Path(path or os.environ.get("IDR_VULKAN_CPU") or PREFIX)


def gpu_icd() -> str | None:
    """A GPU's Vulkan driver manifest on this machine, if any (NVIDIA's or AMD's)."""
    for folder in ("/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d"):
        for name in GPU_ICDS:
            if (Path(folder) / name).is_file():
                return str(Path(folder) / name)
    return None


def resolve(renderer: str, path: str | None = None) -> str:
    """``auto`` -> ``gpu`` where a GPU driver is installed, else ``lavapipe`` when the prefix
    is built, else ``gpu`` (the system's Vulkan, whatever it is). ValueError for a renderer
    that cannot work here, naming the fix."""
    if renderer not in RENDERERS:
        raise ValueError(f"env.params.renderer={renderer!r}: one of {list(RENDERERS)}")
    if renderer == "auto":
        return "gpu" if gpu_icd() or not (prefix(path) / "lvp.json").is_file() else "lavapipe"
    if renderer == "lavapipe" and not (prefix(path) / "lvp.json").is_file():
        raise ValueError(
            f"env.params.renderer=lavapipe: {prefix(path)} has no lavapipe ({SETUP_HINT}; "
            "or set env.params.vulkan_cpu to where it is)"
        )
    return renderer


def configure(path: str | None = None) -> str:
    """Make this process's Vulkan lavapipe with the layer; returns the driver's description.
    Before SAPIEN is imported (its renderer loads Vulkan when first made)."""
    root = prefix(path)
    lib = root / "lib"
    for name in ("libdrm.so.2", "libvulkan.so.1"):  # by path: the driver then links to these
        ctypes.CDLL(str(lib / name), mode=ctypes.RTLD_GLOBAL)
    os.environ["VK_ICD_FILENAMES"] = str(root / "lvp.json")
    os.environ["VK_LAYER_PATH"] = str(root / "layer")
    layers = [x for x in os.environ.get("VK_INSTANCE_LAYERS", "").split(":") if x]
    os.environ["VK_INSTANCE_LAYERS"] = ":".join([*layers, LAYER] if LAYER not in layers else layers)
    version = (root / "VERSION").read_text().strip() if (root / "VERSION").is_file() else "?"
    return f"lavapipe ({version})"
