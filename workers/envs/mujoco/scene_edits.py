"""Scene edits on a MuJoCo model that leave the physics alone: perturbations (camera moved or
pitched, lights dimmed, table recoloured), applied after a reset and restored before the next,
so ``none`` stays the unperturbed scene to the bit; and geoms hidden for one render
(:func:`geoms_hidden`: object-hidden images), restored right after it."""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from workers.envs.wrappers.perturbation_grammar import Perturbation


class MujocoScenePerturber:
    """Scene kinds on a MuJoCo model: each reset restores what the model had when it was built,
    then applies one perturbation, so that ``none`` after any perturbed episode is the
    unperturbed scene to the bit.

    ``camera``: the main camera (moved or pitched); ``table_geoms``: names (or ids) of the geoms
    whose colour ``table_color`` blends (a textured geom's material colour, which tints its
    texture). Lights: every light of the model and the headlight. A simulator that rebuilds
    its model at every reset (LIBERO's hard reset) needs a new perturber per model."""

    DARK = np.array([0.25, 0.15, 0.08])  # table_color's target: dark brown
    DEFAULT_RGBA = np.array([0.5, 0.5, 0.5, 1.0])  # a geom's rgba when its XML sets none

    def __init__(self, model: Any, camera: str, table_geoms: list[str | int]) -> None:
        import mujoco

        self.model = model
        self.cam = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if self.cam < 0:
            raise ValueError(f"perturbations: the scene has no camera {camera!r}")
        self.geoms = [
            g if isinstance(g, int) else mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, g)
            for g in table_geoms
        ]
        if not self.geoms or min(self.geoms) < 0:
            raise ValueError(f"perturbations: the scene lacks a table geom of {table_geoms}")
        self._saved = self._read()

    def _read(self) -> dict[str, np.ndarray]:
        m = self.model
        return {
            "cam_pos": m.cam_pos.copy(),
            "cam_quat": m.cam_quat.copy(),
            "light_diffuse": m.light_diffuse.copy(),
            "light_ambient": m.light_ambient.copy(),
            "light_specular": m.light_specular.copy(),
            "head_diffuse": m.vis.headlight.diffuse.copy(),
            "head_ambient": m.vis.headlight.ambient.copy(),
            "head_specular": m.vis.headlight.specular.copy(),
            "geom_rgba": m.geom_rgba.copy(),
            "mat_rgba": m.mat_rgba.copy(),
        }

    def _colour_of(self, geom: int) -> tuple[tuple[str, int], np.ndarray]:
        """The rgba the renderer shows for ``geom``, as (key, a view into the model): its
        material's when it has one and its own rgba is MuJoCo's default (textured tables:
        LIBERO's), else its own."""
        m = self.model
        mat = int(m.geom_matid[geom])
        if mat >= 0 and np.allclose(m.geom_rgba[geom], self.DEFAULT_RGBA):
            return ("material", mat), m.mat_rgba[mat]
        return ("geom", geom), m.geom_rgba[geom]

    def restore(self) -> None:
        m, s = self.model, self._saved
        m.cam_pos[:], m.cam_quat[:] = s["cam_pos"], s["cam_quat"]
        m.light_diffuse[:], m.light_ambient[:] = s["light_diffuse"], s["light_ambient"]
        m.light_specular[:] = s["light_specular"]
        m.vis.headlight.diffuse[:] = s["head_diffuse"]
        m.vis.headlight.ambient[:] = s["head_ambient"]
        m.vis.headlight.specular[:] = s["head_specular"]
        m.geom_rgba[:] = s["geom_rgba"]
        m.mat_rgba[:] = s["mat_rgba"]

    def apply(self, p: Perturbation, data: Any) -> None:
        """``p`` (a scene kind other than init_jitter, which the env applies to its layout)
        on the restored model; camera and light positions recomputed for the next render."""
        import mujoco

        m = self.model
        if p.kind == "camera_shift":  # sideways: along the world y axis (the table's width)
            m.cam_pos[self.cam, 1] += p.severity
        elif p.kind == "camera_pitch":  # about the camera's own x axis: the view tilts up
            half = np.deg2rad(p.severity) / 2
            turn = np.array([np.cos(half), np.sin(half), 0.0, 0.0])
            out = np.zeros(4)
            mujoco.mju_mulQuat(out, m.cam_quat[self.cam].copy(), turn)
            m.cam_quat[self.cam] = out
        elif p.kind == "light_dim":
            k = 1.0 - p.severity
            m.light_diffuse[:] *= k
            m.light_ambient[:] *= k
            m.light_specular[:] *= k
            m.vis.headlight.diffuse[:] *= k
            m.vis.headlight.ambient[:] *= k
            m.vis.headlight.specular[:] *= k
        elif p.kind == "table_color":
            for rgba in dict(map(self._colour_of, self.geoms)).values():  # a material once
                rgba[:3] = (1 - p.severity) * rgba[:3] + p.severity * self.DARK
        elif p.kind not in ("init_jitter", "distractors"):  # the env's layout, not the model
            raise ValueError(f"{p.kind} is not a scene perturbation of a MuJoCo model")
        mujoco.mj_camlight(m, data)


@contextmanager
def geoms_hidden(model: Any, geoms: Sequence[int]) -> Iterator[None]:
    """``geoms`` (ids) of ``model`` invisible inside the block, as they were to the bit after it
    (even when the block raises).

    A geom whose rgba alpha is 0 is left out of the scene by ``mjv_updateScene``: not drawn,
    not in a segmentation render, no shadow or reflection, and what it covered is seen. Its own
    alpha 0 also outranks its material's colour (MuJoCo uses the material's only while the
    geom's rgba is the default), so textured geoms hide too. Only ``model.geom_rgba`` is
    written, which no physics reads; renders made inside the block see the edit, nothing
    else does once it ends. Not thread-safe on a shared model (one env, one thread)."""
    ids = np.asarray(list(geoms), dtype=np.intp)
    saved = model.geom_rgba[ids].copy()
    model.geom_rgba[ids, 3] = 0.0
    try:
        yield
    finally:
        model.geom_rgba[ids] = saved
