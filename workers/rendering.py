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
from typing import Any


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


def _gl_viewers(env: Any) -> list[Any]:
    """The Gymnasium MuJoCo viewers under ``env`` (a Gymnasium env or wrapper, a vector env's
    sub-envs, or a lerobot env holding the MuJoCo env in ``_env``); none for other envs."""
    viewers: list[Any] = []
    for sub in getattr(env, "envs", None) or [env]:
        base = getattr(sub, "unwrapped", sub)
        for obj in (base, getattr(base, "_env", None)):
            renderer = getattr(obj, "mujoco_renderer", None)
            viewers.extend(getattr(renderer, "_viewers", {}).values())
    return viewers


def own_gl_context(env: Any) -> None:
    """Make the GL context of ``env``'s MuJoCo viewer the current one, before it renders.

    Gymnasium's ``MujocoRenderer`` makes a viewer's context current only when it creates it, so
    in a process holding several MuJoCo envs (one per task, or another suite's env beside this
    one) a frame is drawn in whichever context was made current last; once another env's GL
    objects are freed there, the frames come back black.
    """
    for viewer in _gl_viewers(env):
        viewer.make_context_current()


def release_gl_context(env: Any) -> None:
    """Free ``env``'s MuJoCo GL objects (``MjrContext``) under its own context.

    Left to the garbage collector, ``mjr_freeContext`` runs under whichever context is current
    then, deleting another env's framebuffer (OSMesa numbers objects per context from 1, so the
    names coincide): that env renders black frames from then on.
    """
    for viewer in _gl_viewers(env):
        con = getattr(viewer, "con", None)
        if con is not None:
            viewer.make_context_current()
            con.free()
