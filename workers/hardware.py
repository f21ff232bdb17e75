"""Which hardware and numeric libraries made an episode: its provenance.

The same config and seed give bit-identical tables on one machine, not across machines: torch,
MKL and oneDNN pick kernels by instruction set, llvmpipe compiles shaders for the host, and a
GPU's math settings change float order. So every episode row names its **hardware class**
(the CPU model, the instruction set torch dispatches to, and the GPU where the model computes
on one), and ``run.json`` keeps the full record of each class (library versions, GPU math
settings, the renderer).

    >>> hardware_class({"cpu_model": "AMD EPYC", "cpu_capability": "AVX2", "gpu": None})
    'AMD EPYC / AVX2'
"""

from __future__ import annotations

import os
import platform
import re
from functools import cache
from pathlib import Path
from typing import Any


@cache
def cpu_model() -> str:
    """The CPU's model string (``/proc/cpuinfo``'s model name; the platform's elsewhere)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("model name", "Model", "cpu model")):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def _torch_build() -> dict[str, str | None]:
    """MKL's and oneDNN's versions as torch was built with them."""
    import torch

    text = torch.__config__.show()
    mkl = re.search(r"Math Kernel Library Version ([^\s]+)", text)
    dnn = re.search(r"(?:MKL-DNN|oneDNN) v([^\s]+)", text)
    return {"mkl": mkl.group(1) if mkl else None, "onednn": dnn.group(1) if dnn else None}


def gl_renderer(backend: str | None) -> str | None:
    """The OpenGL implementation MuJoCo renders with (``Mesa 22.3.6 / llvmpipe (LLVM 15.0.6,
    256 bits)`` on the CPU): llvmpipe compiles for the host, so its version and vector width
    are part of the numerics. None where no GL context can be made here."""
    if backend not in ("osmesa", "egl"):
        return None
    try:
        import mujoco
        from OpenGL import GL

        ctx = mujoco.GLContext(8, 8)
        try:
            ctx.make_current()
            version = GL.glGetString(GL.GL_VERSION).decode()
            renderer = GL.glGetString(GL.GL_RENDERER).decode()
        finally:
            ctx.free()
    except Exception:
        return None
    mesa = re.search(r"(Mesa [^\s]+)", version)
    return f"{mesa.group(1) if mesa else version} / {renderer}"


def renderer_in_child(timeout_s: float = 30.0) -> str | None:
    """:func:`gl_renderer` as an actor of this host would see it, read in a child process (the
    caller keeps its own GL settings and imports): the backend ``configure_rendering`` picks."""
    import subprocess
    import sys

    code = (
        "from workers.rendering import configure_rendering\n"
        "from workers.hardware import gl_renderer\n"
        "print(gl_renderer(configure_rendering()) or '')"
    )
    try:
        out = subprocess.run(
            [sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout_s
        )
    except (OSError, subprocess.SubprocessError):
        return None
    lines = out.stdout.strip().splitlines()
    return (lines[-1] or None) if out.returncode == 0 and lines else None


def hardware_record(device: str | None = None, render_backend: str | None = None) -> dict[str, Any]:
    """The hardware class's parts and the numeric libraries of this process. ``device``: where
    the model computes (``cuda...``: the GPU's name, compute capability and math settings are
    recorded); ``render_backend``: the MuJoCo GL backend (its renderer is recorded)."""
    import torch

    rec: dict[str, Any] = {
        "cpu_model": cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "gpu": None,
        "torch": torch.__version__,
        **_torch_build(),
        "torch_threads": torch.get_num_threads(),
        # the switches that pin torch / MKL / oneDNN to an instruction set, where set
        "isa_pins": {
            k: os.environ[k]
            for k in (
                "ATEN_CPU_CAPABILITY",
                "MKL_CBWR",
                "ONEDNN_MAX_CPU_ISA",
                "LP_NATIVE_VECTOR_WIDTH",
            )
            if k in os.environ
        },
    }
    # the installed version, read without importing MuJoCo (a process imports it only once its
    # rendering backend is chosen: workers.rendering)
    try:
        from importlib.metadata import version

        rec["mujoco"] = version("mujoco")
    except Exception:
        rec["mujoco"] = None
    rec["renderer"] = gl_renderer(render_backend)
    if device and str(device).startswith("cuda") and torch.cuda.is_available():
        index = torch.device(device).index or 0
        major, minor = torch.cuda.get_device_capability(index)
        rec["gpu"] = torch.cuda.get_device_name(index)
        rec["gpu_capability"] = f"{major}.{minor}"
        rec["gpu_math"] = {
            "tf32_matmul": torch.backends.cuda.matmul.allow_tf32,
            "tf32_cudnn": torch.backends.cudnn.allow_tf32,
            "cudnn_deterministic": torch.backends.cudnn.deterministic,
            "cudnn_benchmark": torch.backends.cudnn.benchmark,
            "CUBLAS_WORKSPACE_CONFIG": os.environ.get("CUBLAS_WORKSPACE_CONFIG"),
        }
    return rec


def hardware_class(rec: dict[str, Any]) -> str:
    """What decides an episode's float order, in one label: the CPU model and the instruction
    set torch dispatches to, and the GPU where the model computes on one."""
    parts = [str(rec.get("cpu_model") or "unknown"), str(rec.get("cpu_capability") or "unknown")]
    if rec.get("gpu"):
        parts.append(f"{rec['gpu']} (sm {rec.get('gpu_capability', '?')})")
    return " / ".join(parts)
