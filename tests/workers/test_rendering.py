"""Headless rendering is chosen before MuJoCo is imported, and it renders."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest


@pytest.mark.sim
def test_osmesa_renders_a_red_sphere_in_a_fresh_process() -> None:
    code = (
        "from workers.rendering import configure_rendering; b = configure_rendering('osmesa');"
        "import mujoco;"
        "m = mujoco.MjModel.from_xml_string(\"<mujoco><worldbody><light pos='0 0 1'/>"
        "<geom type='sphere' size='.2' rgba='1 0 0 1'/></worldbody></mujoco>\");"
        "d = mujoco.MjData(m); mujoco.mj_forward(m, d); r = mujoco.Renderer(m, 32, 32);"
        "r.update_scene(d); px = r.render(); r.close();"
        "print(b, int(px[..., 0].max()), int(px[..., 2].max()))"
    )
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    r = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env
    )
    assert r.returncode == 0, r.stderr[-2000:]
    backend, red, blue = r.stdout.split()
    assert backend == "osmesa" and int(red) > 100 and int(blue) < int(red)


def test_choosing_after_mujoco_import_is_an_error() -> None:
    code = (
        "import os; os.environ.pop('MUJOCO_GL', None); import mujoco;"
        "from workers.rendering import configure_rendering, RenderingError\n"
        "try:\n    configure_rendering('osmesa')\nexcept RenderingError as e:\n    print('refused:', e)"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert "refused: mujoco was imported before the rendering backend was chosen" in r.stdout, (
        r.stderr
    )


def test_backend_choice_follows_the_gpu(monkeypatch) -> None:
    """EGL where an NVIDIA device is visible, OSMesa otherwise; an explicit MUJOCO_GL wins."""
    import workers.rendering as r

    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setattr(r, "_gpu_visible", lambda: True)
    monkeypatch.setattr(r.sys, "modules", {k: v for k, v in sys.modules.items() if k != "mujoco"})
    assert r.configure_rendering() == "egl" and os.environ["PYOPENGL_PLATFORM"] == "egl"
    monkeypatch.delenv("MUJOCO_GL")
    monkeypatch.setattr(r, "_gpu_visible", lambda: False)
    assert r.configure_rendering() == "osmesa" and os.environ["LP_NUM_THREADS"]
    monkeypatch.setenv("MUJOCO_GL", "egl")
    assert r.configure_rendering() == "egl"


def test_missing_osmesa_names_the_package(monkeypatch) -> None:
    import workers.rendering as r

    monkeypatch.delenv("MUJOCO_GL", raising=False)
    monkeypatch.setattr(r, "_gpu_visible", lambda: False)
    monkeypatch.setattr(r.ctypes.util, "find_library", lambda name: None)
    monkeypatch.setattr(r.sys, "modules", {k: v for k, v in sys.modules.items() if k != "mujoco"})
    with pytest.raises(r.RenderingError, match="libosmesa6"):
        r.configure_rendering()


def test_unknown_backend_is_refused(monkeypatch) -> None:
    import workers.rendering as r

    with pytest.raises(r.RenderingError, match="use 'egl'"):
        r.configure_rendering("vulkan")
