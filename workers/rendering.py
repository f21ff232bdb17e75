"""Choose MuJoCo's headless GL backend inside a worker process, before MuJoCo is imported.

EGL where an NVIDIA GPU is visible, otherwise OSMesa (Debian package libosmesa6). A GL context
made before a fork breaks in the children, so each actor calls this itself. The backend is
recorded with every run: EGL and OSMesa can give slightly different pixels.
"""

from __future__ import annotations

import ctypes.util
import os
import sys
from pathlib import Path


class RenderingError(RuntimeError):
    pass


def _gpu_visible() -> bool:
    if os.environ.get("CUDA_VISIBLE_DEVICES", "x") in ("", "-1"):
        return False
    return Path("/dev/nvidia0").exists()


def configure_rendering(preferred: str | None = None) -> str:
    """Set MUJOCO_GL / PYOPENGL_PLATFORM for this process and return the backend name."""
    backend = preferred or os.environ.get("MUJOCO_GL") or ("egl" if _gpu_visible() else "osmesa")
    if backend not in ("egl", "osmesa", "glfw"):
        raise RenderingError(f"MUJOCO_GL={backend!r}: use 'egl' (GPU) or 'osmesa' (CPU)")
    if "mujoco" in sys.modules and os.environ.get("MUJOCO_GL") != backend:
        raise RenderingError(
            f"mujoco was imported before the rendering backend was chosen ({backend}); "
            "call configure_rendering() first in the worker process"
        )
    if backend == "osmesa" and ctypes.util.find_library("OSMesa") is None:
        raise RenderingError(
            "no headless OpenGL: libOSMesa not found. Install Debian/Ubuntu package libosmesa6 "
            "(make setup does it as root), or run on a GPU node with EGL"
        )
    os.environ["MUJOCO_GL"] = backend
    os.environ["PYOPENGL_PLATFORM"] = backend
    if backend == "osmesa":
        # llvmpipe threads fight the simulator and the other actors for the same cores;
        # one thread per actor measured fastest here (DESIGN.md)
        os.environ.setdefault("LP_NUM_THREADS", "1")
    return backend
