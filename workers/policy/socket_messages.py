"""What travels on a policy socket: a request and its reply, plain values and arrays only (no
pickle), so a peer can send nothing but data.

A request is one flat map (``client``, ``seed``, ``idr``, ``intervention`` and the observation's
fields: :func:`request_message`); replies ``{"ok": True, "step": ...}`` or
``{"ok": False, "type": exception class name, "message": ...}``, each in the env servers' frame
format (``workers.envs.server.wire``). A message of the wrong shape (:func:`check_request`) is
answered with an error before it can reach a batch (``workers.policy.socket_server``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from idr_core.interventions import InterventionConfig
from idr_core.refiner import Diagnostics, RefinerConfig

from workers.backbones.base import Observation
from workers.policy.service import InferRequest
from workers.policy.wrapper import IDRStep


def request_message(request: InferRequest, client: str | None) -> dict[str, Any]:
    obs = request.obs
    return {
        "client": client,
        "seed": request.step_seed,
        "idr": dataclasses.asdict(request.idr),
        "intervention": dataclasses.asdict(request.intervention),
        "images": obs.images,
        "state": obs.state,
        "instruction": list(obs.instruction),
        "do_image": obs.do_image,
        "do_state": obs.do_state,
        "extras": obs.extras,
    }


def request_from_message(msg: dict[str, Any]) -> tuple[InferRequest, str | None]:
    """The request a message holds, checked first (:func:`check_request`: ValueError)."""
    check_request(msg)
    obs = Observation(
        images=msg["images"],
        state=msg["state"],
        instruction=list(msg["instruction"]),
        do_image=msg["do_image"],
        do_state=msg["do_state"],
        extras=msg["extras"],
    )
    request = InferRequest(
        obs,
        int(msg["seed"]),
        RefinerConfig(**msg["idr"]),
        InterventionConfig(**msg["intervention"]),
    )
    return request, msg["client"]


def step_message(step: IDRStep) -> dict[str, Any]:
    out = {f.name: getattr(step, f.name) for f in dataclasses.fields(IDRStep)}
    out["diag"] = None if step.diag is None else step.diag.to_numpy()
    return out


def step_from_message(msg: dict[str, Any]) -> IDRStep:
    diag = msg.pop("diag")
    return IDRStep(**msg, diag=None if diag is None else Diagnostics(**diag))


REQUEST_KEYS = frozenset(
    {"client", "seed", "idr", "intervention", "images", "state", "instruction"}
    | {"do_image", "do_state", "extras"}
)
_ARRAY_KINDS = "biuf"  # bool, ints, floats: what an image or a state may hold
MAX_CLIENT_NAME = 256


def _array(value: Any, what: str, ndim: int) -> np.ndarray:
    if not isinstance(value, np.ndarray) or value.dtype.kind not in _ARRAY_KINDS:
        raise ValueError(f"{what}: expected a numeric array, got {type(value).__name__}")
    if value.ndim != ndim or value.shape[0] != 1:
        raise ValueError(f"{what}: expected {ndim} dims, batch 1; got shape {value.shape}")
    if value.dtype.kind == "f":  # a small array (a state) in Python: a tenth of numpy's cost
        small = value.size <= 1024
        finite = all(map(math.isfinite, value.ravel().tolist())) if small else None
        if not (finite if small else np.isfinite(value).all()):
            raise ValueError(f"{what}: holds NaN or infinity")
    return value


def check_request(msg: Any) -> None:
    """Raise ValueError unless ``msg`` has a request's shape (what ``request_message`` makes:
    its keys, types, an observation of batch 1 with finite numbers). A message that passes
    reaches a batch; one that does not is answered with its error alone, so a peer's malformed
    request never fails its batch mates' forward."""
    if not isinstance(msg, dict) or set(msg) != REQUEST_KEYS:
        keys = sorted(map(str, msg)) if isinstance(msg, dict) else type(msg).__name__
        raise ValueError(f"not a request: keys {keys}, expected {sorted(REQUEST_KEYS)}")
    client = msg["client"]
    if client is not None and not (isinstance(client, str) and len(client) <= MAX_CLIENT_NAME):
        raise ValueError("client: a name of at most 256 characters, or None")
    if isinstance(msg["seed"], bool) or not isinstance(msg["seed"], int):
        raise ValueError(f"seed: an integer, got {type(msg['seed']).__name__}")
    for key in ("idr", "intervention", "extras"):  # the configs check their own fields
        if not isinstance(msg[key], dict):
            raise ValueError(f"{key}: a map")
    images = msg["images"]
    if not isinstance(images, dict) or not all(isinstance(k, str) for k in images):
        raise ValueError("images: a map of camera names to arrays")
    for cam, image in images.items():
        _array(image, f"images[{cam!r}]", 4)
    _array(msg["state"], "state", 2)
    instruction = msg["instruction"]
    if not (
        isinstance(instruction, list) and len(instruction) == 1 and isinstance(instruction[0], str)
    ):
        raise ValueError("instruction: a list of one string (a batch of one)")
    for key in ("do_image", "do_state"):
        if msg[key] is not None:
            _array(msg[key], key, 1)
