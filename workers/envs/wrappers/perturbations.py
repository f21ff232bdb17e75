"""Scene perturbations: the same task with the camera moved, the light dimmed, the table
recoloured, the sensor noisy or blurred, or the objects' start jittered.

A perturbation is ``kind:severity`` (``camera_shift:0.12``) or ``none``. It is a property of
a task: ``env.perturbations`` crosses the run's tasks with a list of them, and a task id names
its perturbation after an ``@`` (``pick_color@camera_shift:0.12``); the unperturbed task keeps
its plain id, so ``none`` is today's episode to the bit. Paired comparisons therefore pair a
cell with its reference on the same perturbed task, episode and seed, and every table of the
report breaks results down by perturbation for free.

Image kinds (``image_noise``, ``image_blur``, ``image_blackout``) act at the sensor, on every camera's rendered
image, for any suite (:class:`PerturbedEnv` applies them). Scene kinds act on the simulator
after its reset and before the first observation, in suites that say they can
(``perturbation_kinds``: the tabletop and LIBERO, both MuJoCo; distractors: the tabletop). Every random draw is seeded by
(seed, task, episode, perturbation): an episode is the same wherever and whenever it runs.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

SEP = "@"  # task id @ perturbation


@dataclass(frozen=True)
class Kind:
    low: float  # severity range, exclusive low / inclusive high
    high: float
    unit: str
    scene: bool  # applied by the env to its simulator (else at the sensor, by PerturbedEnv)
    what: str


KINDS: dict[str, Kind] = {
    "camera_shift": Kind(0.0, 0.3, "m", True, "the main camera moved sideways by SEVERITY m"),
    "camera_pitch": Kind(0.0, 30.0, "deg", True, "the main camera pitched up by SEVERITY deg"),
    "light_dim": Kind(0.0, 1.0, "fraction", True, "every light's intensity scaled by 1 - SEVERITY"),
    "table_color": Kind(
        0.0, 1.0, "fraction", True, "the table's colour blended toward dark brown by SEVERITY"
    ),
    "init_jitter": Kind(
        0.0, 0.02, "m", True, "each object's start moved by up to SEVERITY m in x and y"
    ),
    "distractors": Kind(0.0, 4.0, "objects", True, "SEVERITY extra grey cubes on the table"),
    "image_noise": Kind(0.0, 1.0, "fraction of 255", False, "Gaussian pixel noise, std SEVERITY"),
    "image_blur": Kind(0.0, 5.0, "px", False, "Gaussian blur of std SEVERITY px"),
    # the image-zeroed control: the policy sees black (1) or darkened (< 1) images at every step,
    # executed, not only in the diagnosis's counterfactual pass
    "image_blackout": Kind(
        0.0, 1.0, "fraction", False, "pixels scaled by 1 - SEVERITY (1: a black image)"
    ),
}
SCENE_KINDS = tuple(k for k, v in KINDS.items() if v.scene)
IMAGE_KINDS = tuple(k for k, v in KINDS.items() if not v.scene)
SYNTAX = (
    "write none or KIND:SEVERITY with KIND one of "
    + ", ".join(f"{k} ({v.low:g} < SEVERITY <= {v.high:g} {v.unit})" for k, v in KINDS.items())
    + ", e.g. camera_shift:0.12"
)


@dataclass(frozen=True)
class Perturbation:
    kind: str
    severity: float

    @property
    def text(self) -> str:
        return f"{self.kind}:{self.severity:g}"

    @property
    def scene(self) -> bool:
        return KINDS[self.kind].scene

    def rng(self, seed: int, task_id: str, episode_index: int, *more: int) -> np.random.Generator:
        """The perturbation's random stream for one episode (and, with ``more``, one step and
        camera): a pure function of its arguments."""
        key = zlib.crc32(f"{task_id}{SEP}{self.text}".encode())
        return np.random.default_rng([seed, episode_index, key, *more])


def parse(value: Any) -> Perturbation | None:
    """``none`` / None -> None; ``kind:severity`` or ``{kind, severity}`` -> a Perturbation;
    ValueError naming the allowed kinds and ranges otherwise."""
    if value is None or value == "none":
        return None
    if isinstance(value, Mapping):
        kind, severity = value.get("kind"), value.get("severity")
        extra = set(value) - {"kind", "severity"}
        if extra:
            raise ValueError(f"perturbation {dict(value)}: unknown keys {sorted(extra)}; {SYNTAX}")
    elif isinstance(value, str) and ":" in value:
        kind, _, severity = value.partition(":")
    else:
        raise ValueError(f"perturbation {value!r}: {SYNTAX}")
    if kind not in KINDS:
        raise ValueError(f"perturbation kind {kind!r} is unknown; {SYNTAX}")
    try:
        sev = float(severity)
    except (TypeError, ValueError):
        raise ValueError(f"perturbation {value!r}: severity must be a number; {SYNTAX}") from None
    k = KINDS[kind]
    if k.unit == "objects" and not sev.is_integer():
        raise ValueError(f"perturbation {kind}:{sev:g}: a count of objects is a whole number")
    if not (k.low < sev <= k.high):
        raise ValueError(
            f"perturbation {kind}:{sev:g}: severity out of range, {k.low:g} < severity <= "
            f"{k.high:g} ({k.unit}: {k.what})"
        )
    return Perturbation(kind, sev)


def split_task(task_id: str) -> tuple[str, Perturbation | None]:
    """``pick_color@camera_shift:0.12`` -> (``pick_color``, the perturbation)."""
    base, sep, rest = task_id.partition(SEP)
    return base, (parse(rest) if sep else None)


def join_task(task_id: str, p: Perturbation | None) -> str:
    return task_id if p is None else f"{task_id}{SEP}{p.text}"


def perturbation_of(task_id: str) -> str:
    """The perturbation a task id names, as text (``none`` for a plain id)."""
    _, p = split_task(task_id)
    return "none" if p is None else p.text


# -- at the sensor --------------------------------------------------------------------------------


def perturb_image(image: np.ndarray, p: Perturbation, rng: np.random.Generator) -> np.ndarray:
    """``image`` (uint8 H x W x C) with an image kind applied; a new array."""
    if p.kind == "image_noise":
        noisy = image.astype(np.float32) + rng.normal(0.0, 255.0 * p.severity, image.shape)
        return np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    if p.kind == "image_blur":
        from scipy.ndimage import gaussian_filter

        sigma = (p.severity, p.severity, 0)[: image.ndim]
        out = gaussian_filter(image.astype(np.float32), sigma=sigma, mode="nearest")
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    if p.kind == "image_blackout":
        out = image.astype(np.float32) * (1.0 - p.severity)
        return np.clip(np.rint(out), 0, 255).astype(np.uint8)
    raise ValueError(f"{p.kind} is not an image perturbation")


class PerturbedImages(Mapping[str, np.ndarray]):
    """A lazy image mapping whose images come out perturbed (each camera drawn once)."""

    def __init__(self, images: Mapping[str, np.ndarray], p: Perturbation, rng_for: Any) -> None:
        self._images, self._p, self._rng_for = images, p, rng_for
        self._done: dict[str, np.ndarray] = {}

    def __getitem__(self, camera: str) -> np.ndarray:
        if camera not in self._done:
            image = self._images[camera]
            self._done[camera] = perturb_image(image, self._p, self._rng_for(camera))
        return self._done[camera]

    def __iter__(self) -> Iterator[str]:
        return iter(self._images)

    def __len__(self) -> int:
        return len(self._images)


def perturbed_task(task: Any, p: Perturbation | None) -> Any:
    """``task`` (a TaskSpec) under ``p``: its id names the perturbation; None: unchanged."""
    from dataclasses import replace

    if p is None:
        return task
    return replace(
        task,
        task_id=join_task(task.task_id, p),
        name=f"{task.name} [{p.text}]",
        perturbation=p.kind,
        severity=p.severity,
    )


# -- in a MuJoCo simulator --------------------------------------------------------------------


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


class PerturbedEnv:
    """An env whose tasks are crossed with perturbations (ids ``task@kind:severity``).

    Scene kinds go to the env (its optional ``set_perturbation``, before its reset); image
    kinds are applied here to every image the env renders, lazily, seeded per (seed, task,
    episode, perturbation, step, camera). Everything else is the wrapped env's."""

    def __init__(self, env: Any, perturbations: list[Perturbation | None]) -> None:
        self._env = env
        self._perturbations = list(perturbations) or [None]
        self._p: Perturbation | None = None
        self._episode: tuple[str, int, int] = ("", 0, 0)

    def __getattr__(self, name: str) -> Any:  # the env's members (optional ones included)
        return getattr(self._env, name)

    def tasks(self) -> list[Any]:
        return [perturbed_task(t, p) for t in self._env.tasks() for p in self._perturbations]

    def reset(self, task_id: str, episode_index: int, seed: int) -> Any:
        from workers.envs.base import suite_hooks, suite_info

        base, p = split_task(task_id)
        setter = suite_hooks(self._env).set_perturbation
        if p is not None and p.scene:
            if setter is None or p.kind not in suite_info(self._env).perturbation_kinds:
                raise ValueError(
                    f"{task_id}: suite {getattr(self._env, 'suite', '?')!r} cannot apply "
                    f"{p.kind}; image kinds ({', '.join(IMAGE_KINDS)}) work with any suite"
                )
            setter(p)
        elif setter is not None:
            setter(None)
        obs = self._env.reset(base, episode_index, seed)
        self._p, self._episode = p, (task_id, episode_index, seed)
        return self._wrap(obs)

    def step(self, action: np.ndarray) -> Any:
        return self._wrap(self._env.step(action))

    def _wrap(self, obs: Any) -> Any:
        from dataclasses import replace

        p = self._p
        if p is None or p.scene:
            return obs
        task_id, episode, seed = self._episode
        step = int(self._env.steps)

        def rng_for(camera: str) -> np.random.Generator:
            return p.rng(seed, task_id, episode, step, zlib.crc32(camera.encode()))

        return replace(obs, images=PerturbedImages(obs.images, p, rng_for))

    @property
    def task(self) -> Any:
        return perturbed_task(self._env.task, self._p)
