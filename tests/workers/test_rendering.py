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
