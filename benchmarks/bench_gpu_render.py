"""Offscreen MuJoCo rendering per frame with the backend workers/rendering.py picks (EGL on GPU).

The scene is plain MuJoCo, not the tabletop env (that needs robosuite): a floor, a table, five
free boxes, two lights and two cameras (agentview, wrist), stepped between frames so that each
frame differs. Per image size it times ``update_scene + render`` (the pixels read back to host
memory, as an env returns them) for one camera and for two, and ``mj_step`` alone.

Writes ``benchmarks/results/gpu_rendering.json``.
Usage: ``python benchmarks/bench_gpu_render.py [--sizes 96,128,224] [--frames 300] [--backend egl]``
(without ``--backend`` the choice is workers.rendering.configure_rendering()'s: EGL where
/dev/nvidia0 exists, else OSMesa).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results" / "gpu_rendering.json"

SCENE = """
<mujoco model="idr_render_bench">
  <visual><global offwidth="512" offheight="512"/><quality shadowsize="2048"/></visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".2 .3 .4" rgb2=".3 .4 .5"
             width="256" height="256"/>
    <material name="grid" texture="grid" texrepeat="4 4" reflectance=".1"/>
  </asset>
  <worldbody>
    <light pos="0 0 3" dir="0 0 -1" castshadow="true"/>
    <light pos="1 1 2" dir="-1 -1 -1" diffuse=".4 .4 .4"/>
    <geom type="plane" size="2 2 .1" material="grid"/>
    <geom name="table" type="box" pos="0 0 .4" size=".5 .4 .02" rgba=".6 .45 .3 1"/>
    BOXES
    <camera name="agentview" pos="1.0 0 1.1" xyaxes="0 1 0 -0.6 0 0.8"/>
    <body name="wrist" pos="0 0 .9">
      <camera name="wrist" pos="0 0 0" xyaxes="1 0 0 0 1 0"/>
    </body>
  </worldbody>
</mujoco>
"""
COLORS = ("1 0 0 1", "0 1 0 1", "0 0 1 1", "1 1 0 1", "0 1 1 1")


def scene_xml() -> str:
    boxes = "\n".join(
        f'<body pos="{-0.3 + 0.15 * i:.2f} {0.1 * (i % 2):.2f} {0.5 + 0.05 * i:.2f}">'
        f'<freejoint/><geom type="box" size=".03 .03 .03" rgba="{c}"/></body>'
        for i, c in enumerate(COLORS)
    )
    return SCENE.replace("BOXES", boxes)


def _gl_strings() -> dict[str, str]:
    """GL vendor/renderer of the current context (PyOpenGL), where it can be read."""
    try:
        from OpenGL import GL

        return {
            "gl_vendor": GL.glGetString(GL.GL_VENDOR).decode(),
            "gl_renderer": GL.glGetString(GL.GL_RENDERER).decode(),
            "gl_version": GL.glGetString(GL.GL_VERSION).decode(),
        }
    except Exception as e:
        return {"gl_strings_error": f"{type(e).__name__}: {e}"[:300]}


def measure(size: int, frames: int, warmup: int, cameras: tuple[str, ...]) -> dict[str, Any]:
    import mujoco

    model = mujoco.MjModel.from_xml_string(scene_xml())
    data = mujoco.MjData(model)
    renderer = mujoco.Renderer(model, height=size, width=size)
    try:
        render_ms: list[float] = []
        step_ms: list[float] = []
        for f in range(warmup + frames):
            t0 = time.perf_counter()
            mujoco.mj_step(model, data)
            t1 = time.perf_counter()
            imgs = []
            for cam in cameras:
                renderer.update_scene(data, camera=cam)
                imgs.append(renderer.render())
            t2 = time.perf_counter()
            if f >= warmup:
                step_ms.append((t1 - t0) * 1e3)
                render_ms.append((t2 - t1) * 1e3)
        img = imgs[0]
        means = [round(float(i.mean()), 1) for i in imgs]  # not black: the scene was drawn
        gl = _gl_strings()
        return {
            "image_size": size,
            "cameras": len(cameras),
            "render_ms_per_step_median": statistics.median(render_ms),
            "render_ms_per_frame_median": statistics.median(render_ms) / len(cameras),
            "render_ms_p90": sorted(render_ms)[int(0.9 * (len(render_ms) - 1))],
            "fps_frames": len(cameras) * 1e3 / statistics.median(render_ms),
            "mj_step_ms_median": statistics.median(step_ms),
            "frames": frames,
            "last_image_means": means,
            "image_shape": list(img.shape),
            **gl,
        }
    finally:
        renderer.close()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="96,128,224")
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--warmup", type=int, default=20)
    ap.add_argument("--backend", default=None, help="egl / osmesa (default: auto)")
    ap.add_argument("--out", type=Path, default=RESULTS)
    args = ap.parse_args()

    env_before = os.environ.get("MUJOCO_GL")
    from workers.rendering import configure_rendering

    backend = configure_rendering(args.backend)
    import mujoco

    results: dict[str, Any] = {
        "machine": {
            **machine_record(),
            "python": platform.python_version(),
            "mujoco": mujoco.__version__,
            "dev_nvidia0": Path("/dev/nvidia0").exists(),
        },
        "backend": backend,
        "backend_picked_by": (
            "--backend"
            if args.backend
            else ("MUJOCO_GL" if env_before else "workers.rendering auto")
        ),
        "scene": (
            "plain MuJoCo scene (floor, table, 5 free boxes, 2 lights with shadows, cameras "
            "agentview + wrist), not the robosuite tabletop env (robosuite is too large to "
            "carry to the GPU machine); timing = update_scene + render incl. readback to host"
        ),
        "rows": [],
    }
    try:
        import torch

        if torch.cuda.is_available():
            results["machine"]["device_name"] = torch.cuda.get_device_name(0)
    except Exception:
        pass
    for size in [int(s) for s in args.sizes.split(",") if s]:
        for cams in (("agentview",), ("agentview", "wrist")):
            row = measure(size, args.frames, args.warmup, cams)
            results["rows"].append(row)
            print(
                f"{backend} {size:>4}px x{len(cams)} cam: "
                f"{row['render_ms_per_frame_median']:.3f} ms/frame, "
                f"mj_step {row['mj_step_ms_median']:.3f} ms, mean px {row['last_image_means']}",
                flush=True,
            )
    results["gl"] = {
        k: v for k, v in results["rows"][0].items() if k.startswith("gl_")
    }  # one context's strings
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
