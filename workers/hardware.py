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
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from pathlib import Path
from typing import Any

PINS = ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "ONEDNN_MAX_CPU_ISA", "LP_NATIVE_VECTOR_WIDTH")


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


@cache
def renderer_in_child(timeout_s: float = 30.0) -> str | None:
    """:func:`gl_renderer` as an actor of this host would see it, read in a child process (the
    caller keeps its own GL settings and imports): the backend ``configure_rendering`` picks.
    Read once per process: a host's renderer does not change while a driver runs."""
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
        "isa_pins": {k: os.environ[k] for k in PINS if k in os.environ},
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


def machine_record(device: str | None = None) -> dict[str, Any]:
    """What a benchmark result names its machine by: the CPU model and the instruction set torch
    dispatches to (the hardware class), core count, Python and torch; the GPU's name where
    ``device`` is one. Cheap: no GL context, no child process."""
    import torch

    rec: dict[str, Any] = {
        "cpu_model": cpu_model(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "cpus": os.cpu_count(),
        "python": platform.python_version(),
        "torch": torch.__version__,
    }
    if device and str(device).startswith("cuda") and torch.cuda.is_available():
        rec["device_name"] = torch.cuda.get_device_name(torch.device(device).index or 0)
    return rec


#: ``executor.numerics_mode: portable``: what decides CPU float order, pinned in every process
#: that holds a model or renders, before its first kernel runs. torch's kernels, MKL and oneDNN
#: to AVX2 (the widest set common to the x86 CPUs of a mixed cluster: AVX-512 machines would
#: otherwise take other kernels), MKL's conditional numerical reproducibility in strict mode,
#: and llvmpipe's vector width to 256 bits (it compiles shaders for the host otherwise).
PORTABLE_ISA = "AVX2"
PORTABLE_ENV = {
    "ATEN_CPU_CAPABILITY": "avx2",
    "MKL_CBWR": "AVX2,STRICT",
    "ONEDNN_MAX_CPU_ISA": "AVX2",
    "LP_NATIVE_VECTOR_WIDTH": "256",
}


def numerics_env(mode: str) -> dict[str, str]:
    """The environment a process of ``executor.numerics_mode`` sets before its first kernel."""
    return dict(PORTABLE_ENV) if mode == "portable" else {}


def apply_numerics_env(env: dict[str, str]) -> None:
    """Set ``env`` in this process. torch reads its capability, MKL its CBWR and oneDNN its ISA
    at their first kernel, llvmpipe its vector width at its first context: call this before the
    process computes or renders anything (an actor's first act)."""
    os.environ.update(env)


@contextmanager
def numerics_env_for_now(env: dict[str, str]) -> Iterator[None]:
    """``env`` set in this process inside the block, the earlier values back after it: a
    record taken as another process will see it, leaving this one's environment (and that of
    the processes it starts later) as it was."""
    before = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def cpu_flags() -> set[str]:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def check_portable_cpu() -> str | None:
    """Why this CPU cannot run the portable mode (None: it can): AVX2 and FMA are needed."""
    if platform.machine().lower() not in ("x86_64", "amd64"):
        return f"{platform.machine()} is not x86-64"
    missing = {"avx2", "fma"} - cpu_flags()
    return f"{cpu_model()} lacks {', '.join(sorted(missing))}" if missing else None


def is_portable(rec: dict[str, Any]) -> bool:
    """Whether ``rec`` was taken under the portable pins, and torch honoured them."""
    pins = rec.get("isa_pins") or {}
    return all(pins.get(k) == v for k, v in PORTABLE_ENV.items()) and (
        str(rec.get("cpu_capability")) == PORTABLE_ISA
    )


def hardware_class(rec: dict[str, Any]) -> str:
    """What decides an episode's float order, in one label: the CPU model and the instruction
    set torch dispatches to, and the GPU where the model computes on one. Under the portable
    pins the CPU reduces to the pinned instruction set (``portable AVX2``)."""
    if is_portable(rec):
        parts = [f"portable {PORTABLE_ISA}"]
    else:
        parts = [
            str(rec.get("cpu_model") or "unknown"),
            str(rec.get("cpu_capability") or "unknown"),
        ]
    if rec.get("gpu"):
        parts.append(f"{rec['gpu']} (sm {rec.get('gpu_capability', '?')})")
    return " / ".join(parts)
