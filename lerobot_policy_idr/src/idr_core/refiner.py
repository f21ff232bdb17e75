"""The causality-aware action refiner of IDR (paper, section Method), on plain arrays.

This module knows nothing about models or simulators: it takes the factual action and the
two counterfactual actions (image intervened, state intervened) and returns the refined
action plus per-sample diagnostics. It works on numpy arrays and on torch tensors (on any
device, without copying to the host), batch first, with any trailing action shape: norms
are taken per sample over all trailing dims, so for (B, T, D) chunks the whole chunk is
one vector.

Equations (guidance ``visual``; ``proprio`` swaps the roles of image and state):

    d_img  = a_base - a_no_img          d_prop = a_base - a_no_prop
    e_img  = ||d_img||_2                e_prop = ||d_prop||_2
    g      = 1[e_img < tau]
    w_prop = beta * min(1, e_prop / (e_img + eps))
    u_prop = clip(d_prop, -lam, lam)
    a_final = a_base + g * (alpha * d_img + w_prop * u_prop)
    r_img  = e_img / (e_img + e_prop + eps)

Besides the paper's modes (E and the ablations A-D, F), three controls keep E's gate and
change only its correction ``c = alpha * d_img + w_prop * u_prop``:

    random      a_final = a_base + g * ||c|| * r / ||r||,  r ~ N(0, I) over the chunk (seeded)
    shuffled    a_final = a_base + g * c[..., perm],       perm a derangement of the action dims
    scale_free  a_final = a_base + g * (alpha * d_img / (e_img + eps) + w_prop * u_prop)

``random`` and ``shuffled`` are placebos: a push of E's size (and, for ``shuffled``, E's time
structure and values) in a direction unrelated to the diagnosed effect; ``scale_free`` keeps
E's direction but fixes the main term's norm to alpha, so its size does not grow with the
base's action scale. The methods that are not a refinement of three passes (image guidance,
ensembles, the object-hidden contrast) are in ``idr_core.methods``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Literal, get_args

import numpy as np

from idr_core.tensors import is_torch

Mode = Literal[
    "baseline",
    "diagnose",
    "A",
    "B",
    "C",
    "D",
    "E",
    "F",
    "random",
    "shuffled",
    "scale_free",
    "cfg",
    "ensemble",
    "temporal",
    "pcd",
]
Guidance = Literal["visual", "proprio"]

MODES: tuple[str, ...] = get_args(Mode)
GUIDANCES: tuple[str, ...] = get_args(Guidance)

#: What each mode does, for help texts and reports.
MODE_DESCRIPTIONS: dict[str, str] = {
    "baseline": "backbone only: no counterfactual passes, executes a_base",
    "diagnose": "three passes, executes a_base, records diagnostics",
    "A": "no proprioceptive stabilizer term",
    "B": "stabilizer not clipped to [-lam, lam]",
    "C": "stabilizer weight fixed to beta (not adaptive)",
    "D": "no gate: refinement at every step (g = 1)",
    "E": "full method",
    "F": "alpha and beta negated (refines against the diagnosed effect)",
    "random": "placebo: E's gate and correction norm, in a random direction (step seed)",
    "shuffled": "placebo: E's correction with its action dims permuted (time structure kept)",
    "scale_free": "E with the visual term divided by E_img (its norm is alpha)",
    "cfg": "image guidance, classifier-free style: a_base + w * d_img, no gate, no stabilizer",
    "ensemble": "the mean of `samples` chunks drawn with independent noise (sampling bases)",
    "temporal": "temporal ensembling (lerobot's ACTTemporalEnsembler): inference every step",
    "pcd": "policy contrastive decoding: a_base + w * (a_base - a_objects_hidden)",
}
#: Modes that refine three passes with E's gate (the paper's modes and the controls of E).
REFINER_MODES: tuple[str, ...] = ("A", "B", "C", "D", "E", "F", "random", "shuffled", "scale_free")


@dataclass(frozen=True)
class RefinerConfig:
    """Refiner parameters. Defaults are the paper's (pi0.5 on LIBERO).

    The harness and the plugin both import it from here. ``IDRConfig`` is the lerobot policy
    config (``configuration_idr.IDRConfig``), whose fields of the same names build one of these
    (lerobot derives a policy class from its config class's name)."""

    alpha: float = 0.08  # strength of the main (visual) correction
    beta: float = 0.05  # strength of the bounded stabilizer (proprioceptive) term
    lam: float = 0.1  # clip bound of the stabilizer residual
    tau: float = 7.0  # gate threshold on the main effect's norm (paper: mean E_img of baseline)
    eps: float = 1e-6  # keeps ratios finite when an effect is exactly zero
    mode: str = "E"  # one of MODES
    guidance: str = "visual"  # which modality's effect drives the correction
    # the settings of the methods beside IDR (idr_core.methods says which mode reads which)
    w: float = 0.08  # guidance weight of cfg and pcd (default: IDR's alpha, the same push)
    samples: int = 3  # chunks averaged by ensemble (3: IDR's forwards)
    te_coeff: float = 0.01  # temporal ensembling's coefficient (lerobot's ACT default)
    horizon: int | None = None  # actions executed per inference; None: the runtime's default
    # a refined action is clipped into the base's action bounds (the dataset's min/max, widened
    # to the base action itself) where the base knows them: clip_into
    clip_actions: bool = True

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(
                f"RefinerConfig.mode={self.mode!r} is unknown; allowed values: {MODES}"
            )
        if self.guidance not in GUIDANCES:
            raise ValueError(
                f"RefinerConfig.guidance={self.guidance!r} is unknown; allowed values: {GUIDANCES}"
            )
        for name in ("alpha", "beta", "lam", "tau"):
            value = getattr(self, name)
            if not isinstance(value, int | float) or math.isnan(value) or value < 0:
                raise ValueError(
                    f"RefinerConfig.{name}={value!r} must be a number >= 0 "
                    "(mode 'F' negates alpha and beta itself; tau may be inf for 'always on')"
                )
        if not isinstance(self.eps, int | float) or not (0 < self.eps < math.inf):
            raise ValueError(f"RefinerConfig.eps={self.eps!r} must be a finite number > 0")
        for name in ("w", "te_coeff"):
            value = getattr(self, name)
            if (
                isinstance(value, bool)
                or not isinstance(value, int | float)
                or not math.isfinite(value)
            ):
                raise ValueError(f"RefinerConfig.{name}={value!r} must be a finite number")
        if not isinstance(self.clip_actions, bool):
            raise ValueError(
                f"RefinerConfig.clip_actions={self.clip_actions!r} must be true or false"
            )
        if isinstance(self.samples, bool) or not isinstance(self.samples, int) or self.samples < 2:
            raise ValueError(
                f"RefinerConfig.samples={self.samples!r} must be an integer >= 2 (chunks averaged)"
            )
        if self.horizon is not None and (
            isinstance(self.horizon, bool) or not isinstance(self.horizon, int) or self.horizon < 1
        ):
            raise ValueError(
                f"RefinerConfig.horizon={self.horizon!r} must be an integer >= 1 or null "
                "(null: the runtime's default, executor replan_steps / n_action_steps)"
            )

    @property
    def needs_counterfactuals(self) -> bool:
        """Whether the mode runs the two counterfactual passes."""
        return self.mode != "baseline"

    @property
    def refines(self) -> bool:
        """Whether the executed action may differ from a_base."""
        return self.mode not in ("baseline", "diagnose")

    @property
    def gated(self) -> bool:
        """Whether the mode refines three passes under E's gate (so reads tau, except D)."""
        return self.mode in REFINER_MODES

    def with_(self, **changes: Any) -> RefinerConfig:
        return replace(self, **changes)


@dataclass(frozen=True)
class Diagnostics:
    """Per-sample diagnostics, each of shape (B,), same array type/device/dtype as the actions.

    ``gate`` is the gate the mode computes (1.0 = refinement applied). In ``diagnose`` mode it
    is the gate the full method *would* apply; the executed action is a_base regardless.
    ``w_prop`` is the weight of the stabilizer term (under ``proprio`` guidance the stabilizer
    is the image residual); it is 0 in mode A.
    """

    e_img: Any
    e_prop: Any
    r_img: Any
    gate: Any
    w_prop: Any

    def to_numpy(self) -> dict[str, np.ndarray]:
        return {
            k: _to_numpy(getattr(self, k)) for k in ("e_img", "e_prop", "r_img", "gate", "w_prop")
        }


def _to_numpy(x: Any) -> np.ndarray:
    if is_torch(x):
        return x.detach().cpu().numpy()
    return np.asarray(x)


class _Ops:
    """The handful of array operations the refiner needs, for numpy or torch."""

    def __init__(self, torch_mode: bool) -> None:
        self.torch = torch_mode
        if torch_mode:
            import torch

            self._t = torch

    def norm(self, x: Any) -> Any:
        flat = x.reshape(x.shape[0], -1)
        if self.torch:
            return self._t.linalg.vector_norm(flat, dim=1)
        return np.linalg.norm(flat, axis=1).astype(x.dtype, copy=False)

    def clip(self, x: Any, lo: float, hi: float) -> Any:
        if self.torch:
            return self._t.clamp(x, lo, hi)
        return np.clip(x, lo, hi)

    def min_one(self, x: Any) -> Any:
        if self.torch:
            return self._t.clamp(x, max=1.0)
        return np.minimum(x, 1.0)

    def indicator(self, cond: Any, like: Any) -> Any:
        if self.torch:
            return cond.to(like.dtype)
        return cond.astype(like.dtype)

    def full_like(self, x: Any, value: float) -> Any:
        if self.torch:
            return self._t.full_like(x, value)
        return np.full_like(x, value)

    def all_finite(self, x: Any) -> bool:
        if self.torch:
            return bool(self._t.isfinite(x).all())
        return bool(np.isfinite(x).all())

    def is_float(self, x: Any) -> bool:
        if self.torch:
            return x.is_floating_point()
        return np.issubdtype(x.dtype, np.floating)


def _validate(a_base: Any, a_no_img: Any, a_no_prop: Any) -> _Ops:
    named = {"a_base": a_base, "a_no_img": a_no_img, "a_no_prop": a_no_prop}
    kinds = {name: is_torch(x) for name, x in named.items()}
    if len(set(kinds.values())) != 1:
        raise ValueError(
            f"actions must all be numpy arrays or all torch tensors, got {kinds} (True = torch)"
        )
    ops = _Ops(torch_mode=kinds["a_base"])
    for name, x in named.items():
        if not ops.torch and not isinstance(x, np.ndarray):
            raise ValueError(
                f"{name} must be a numpy array or torch tensor, got {type(x).__name__}"
            )
        if x.ndim < 2:
            raise ValueError(
                f"{name} has shape {tuple(x.shape)}: actions are batch first, (B, D) or (B, T, D)"
            )
        if not ops.is_float(x):
            raise ValueError(f"{name} has dtype {x.dtype}: actions must be floating point")
    shapes = {name: tuple(x.shape) for name, x in named.items()}
    if len(set(shapes.values())) != 1:
        raise ValueError(f"action shapes differ: {shapes}; all three must have the same shape")
    dtypes = {name: str(x.dtype) for name, x in named.items()}
    if len(set(dtypes.values())) != 1:
        raise ValueError(f"action dtypes differ: {dtypes}; all three must have the same dtype")
    if ops.torch:
        devices = {name: str(x.device) for name, x in named.items()}
        if len(set(devices.values())) != 1:
            raise ValueError(f"action devices differ: {devices}; put all three on one device")
    for name, x in named.items():
        if not ops.all_finite(x):
            raise ValueError(f"{name} contains NaN or inf; the refiner needs finite actions")
    return ops


def refine(
    a_base: Any, a_no_img: Any, a_no_prop: Any, cfg: RefinerConfig, seed: int = 0
) -> tuple[Any, Diagnostics]:
    """Refine ``a_base`` from the two counterfactual actions; see the module docstring.

    Returns ``(a_final, diag)``; ``a_final`` has the shape, dtype and device of ``a_base``.
    In modes ``baseline`` and ``diagnose`` ``a_final`` is ``a_base`` (diagnostics still computed);
    the modes of ``idr_core.methods`` that are not refinements give ``a_base`` here too.
    ``seed`` draws the placebo's direction (``random``) or permutation (``shuffled``): the
    harness passes the step seed, the lerobot policy a draw from torch's RNG."""
    ops = _validate(a_base, a_no_img, a_no_prop)
    d_img = a_base - a_no_img
    d_prop = a_base - a_no_prop
    e_img = ops.norm(d_img)
    e_prop = ops.norm(d_prop)
    r_img = e_img / (e_img + e_prop + cfg.eps)

    # The main correction follows the guided modality; the other one is the stabilizer.
    if cfg.guidance == "visual":
        d_main, d_aux, e_main, e_aux = d_img, d_prop, e_img, e_prop
    else:
        d_main, d_aux, e_main, e_aux = d_prop, d_img, e_prop, e_img

    alpha, beta = (-cfg.alpha, -cfg.beta) if cfg.mode == "F" else (cfg.alpha, cfg.beta)
    gate = (
        ops.full_like(e_main, 1.0) if cfg.mode == "D" else ops.indicator(e_main < cfg.tau, e_main)
    )
    if cfg.mode == "A":
        w_aux = ops.full_like(e_main, 0.0)
    elif cfg.mode == "C":
        w_aux = ops.full_like(e_main, beta)
    else:
        w_aux = beta * ops.min_one(e_aux / (e_main + cfg.eps))
    u_aux = d_aux if cfg.mode == "B" else ops.clip(d_aux, -cfg.lam, cfg.lam)

    diag = Diagnostics(e_img=e_img, e_prop=e_prop, r_img=r_img, gate=gate, w_prop=w_aux)
    if not cfg.gated:
        return a_base, diag

    trailing = (1,) * (a_base.ndim - 1)
    g = gate.reshape(-1, *trailing)
    w = w_aux.reshape(-1, *trailing)
    if cfg.mode == "scale_free":
        main = alpha * d_main / (e_main.reshape(-1, *trailing) + cfg.eps)
    else:
        main = alpha * d_main
    correction = main + w * u_aux
    if cfg.mode == "random":
        correction = _random_push(ops, correction, seed)
    elif cfg.mode == "shuffled":
        correction = correction[..., derangement(correction.shape[-1], seed)]
    return a_base + g * correction, diag


def clip_into(final: Any, a_base: Any, lo: Any, hi: Any) -> tuple[Any, list[int]]:
    """``final`` clipped into ``[min(lo, a_base), max(hi, a_base)]`` per action dim (``lo`` /
    ``hi``: the base's dataset action min/max, (D,)), and the elements clipped per sample. The
    bounds widen to the base action itself, so a base that leaves its data's range is never
    pulled back: only what a refinement added beyond it is cut."""
    b = final.shape[0]
    if is_torch(final):
        import torch

        lo_t = torch.as_tensor(np.asarray(lo), dtype=final.dtype, device=final.device)
        hi_t = torch.as_tensor(np.asarray(hi), dtype=final.dtype, device=final.device)
        low, high = torch.minimum(lo_t, a_base), torch.maximum(hi_t, a_base)
        bounded = torch.maximum(torch.minimum(final, high), low)
        return bounded, (bounded != final).reshape(b, -1).sum(dim=1).tolist()
    final_np, base_np = np.asarray(final), np.asarray(a_base)
    low = np.minimum(np.asarray(lo, dtype=final_np.dtype), base_np)
    high = np.maximum(np.asarray(hi, dtype=final_np.dtype), base_np)
    bounded = np.maximum(np.minimum(final_np, high), low)
    return bounded, (bounded != final_np).reshape(b, -1).sum(axis=1).tolist()


def derangement(n: int, seed: int) -> np.ndarray:
    """A permutation of ``n`` indices that moves every index (drawn from ``seed``); the
    identity for ``n == 1``, which has no other."""
    rng = np.random.default_rng(seed)
    if n == 1:
        return np.zeros(1, dtype=np.int64)
    while True:
        perm = rng.permutation(n)
        if not (perm == np.arange(n)).any():
            return perm


def _random_push(ops: _Ops, correction: Any, seed: int) -> Any:
    """``correction``'s per-sample norm in a direction drawn isotropically over the sample's
    trailing dims (the chunk's steps and action dims) from ``seed``."""
    r = np.random.default_rng(seed).standard_normal(tuple(correction.shape))
    r /= np.linalg.norm(r.reshape(r.shape[0], -1), axis=1).reshape(-1, *(1,) * (r.ndim - 1))
    if ops.torch:
        r = ops._t.as_tensor(r, dtype=correction.dtype, device=correction.device)
    else:
        r = r.astype(correction.dtype)
    size = ops.norm(correction).reshape(-1, *(1,) * (correction.ndim - 1))
    return size * r
