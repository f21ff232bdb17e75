"""``backbone.kind: remote``: a policy served elsewhere, over openpi's websocket protocol.

The server (openpi's ``serve_policy.py``, ``openpi-server``, or any server speaking the same
protocol around OpenVLA-OFT, VLA-Adapter...) sends its metadata on connect, then answers each
observation dict (msgpack-numpy, ``workers.backbones.websocket.codec``) with a dict holding
``actions``: a (T, D) chunk, or (B, T, D) for a batched request. A text frame instead of a
reply is the server's traceback: it becomes the episode's error, in the server's words.

Keys: ``key_map`` names where each of our inputs goes in the server's dict; presets for openpi's
LIBERO example (``openpi_libero``) and for OFT-style servers (``oft``). Images are sent as
uint8 (H, W, 3), as the env rendered them (the server resizes, as openpi's clients expect).

IDR's three passes: the wrapper calls ``predict_chunk`` with a batch of 3 (factual, do(V),
do(S), interventions applied here on the raw observation). When the server's metadata says
``{"idr": {"batch": true}}`` the batch goes as one request (arrays with a leading batch dim,
``prompt`` a list); otherwise as one request per row on the same connection. With
``{"idr": {"noise": true}}`` (openpi's policies take a ``noise`` array) each row carries the
episode's noise for this inference, shared by the three passes (``crn``); otherwise none.

Bounds: a frame from the server longer than ``max_reply_bytes`` (16 MiB: a reply is an action
chunk, metadata a small map) ends the connection with ``RemoteBackboneError`` before it is read
whole (the websockets library enforces it as frames arrive).

Faults: connect and read timeouts (``timeout_s``) and a connection that drops raise
``RemoteBackboneError``; the episode becomes an error row and the scheduler runs it again,
and the next call connects anew.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Mapping
from typing import Any, ClassVar

import numpy as np

from workers.backbones.base import Observation
from workers.backbones.websocket import codec
from workers.io_spec import EnvIO, PolicyIO

log = logging.getLogger(__name__)
RECONNECT_S = 0.25  # between tries to connect to a server that is not up (restarting)
# the longest frame taken from a policy server: a (B, T, D) float chunk is kilobytes; openpi's
# own client takes any size, which lets whatever answers at host:port fill this process
MAX_REPLY_BYTES = 16 << 20

# our input -> the server's key; "image:<camera>" for an env camera, "state", "prompt"
KEY_PRESETS: dict[str, dict[str, str]] = {
    # openpi's examples/libero/main.py
    "openpi_libero": {
        "image:agentview": "observation/image",
        "image:wrist": "observation/wrist_image",
        "state": "observation/state",
        "prompt": "prompt",
    },
    # OpenVLA-OFT-style servers (full_image / wrist_image / state / instruction)
    "oft": {
        "image:agentview": "full_image",
        "image:wrist": "wrist_image",
        "state": "state",
        "prompt": "instruction",
    },
}


class RemoteBackboneError(RuntimeError):
    """The policy server cannot be reached, timed out, dropped the connection or answered
    something that is not this protocol."""


def _to_uint8_hwc(image: Any) -> np.ndarray:
    """(3, H, W) floats in [0, 1] (our policy convention) back to the (H, W, 3) uint8 the env
    rendered (exact for images made by workers.episode.observation.image_to_tensor)."""
    x = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    return np.rint(np.clip(x, 0, 1) * 255).astype(np.uint8).transpose(1, 2, 0)


class WebsocketBackbone:
    """A backbone whose model runs in a policy server (see the module docstring)."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset()
    can_batch = True  # predict_chunk takes any batch (one request, or one per row)
    remote = True  # the server's forward shapes and float order are its own

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 8000,
        key_map: str | dict[str, str] = "openpi_libero",
        timeout_s: float = 30.0,
        chunk_len: int | None = None,
        action_dim: int | None = None,
        noise_shape: list[int] | None = None,
        max_reply_bytes: int = MAX_REPLY_BYTES,
    ) -> None:
        if isinstance(key_map, str):
            if key_map not in KEY_PRESETS:
                raise ValueError(
                    f"backbone.params.key_map={key_map!r}: a preset of {sorted(KEY_PRESETS)} or "
                    "a mapping {image:<camera> | state | prompt: <server key>}"
                )
            key_map = KEY_PRESETS[key_map]
        bad = [k for k in key_map if not (k in ("state", "prompt") or k.startswith("image:"))]
        if bad:
            raise ValueError(
                f"backbone.params.key_map: {bad} are not inputs; use image:<camera>, state, prompt"
            )
        self.host, self.port, self.timeout_s = host, int(port), float(timeout_s)
        if int(max_reply_bytes) < 1:
            raise ValueError("backbone.params.max_reply_bytes must be >= 1")
        self.max_reply_bytes = int(max_reply_bytes)
        self.key_map = dict(key_map)
        self.cameras = tuple(k.split(":", 1)[1] for k in self.key_map if k.startswith("image:"))
        self.name = f"remote:{host}:{port}"
        self._ws: Any = None
        self.metadata: dict[str, Any] = {}
        self.connect()
        idr = self.metadata.get("idr") or {}
        self.server_batches = bool(idr.get("batch", False))
        self.server_takes_noise = bool(idr.get("noise", False))
        self.chunk_len = int(chunk_len or self.metadata.get("action_horizon") or 0)
        self.action_dim = int(action_dim or self.metadata.get("action_dim") or 0)
        self.declared_action_dim = self.action_dim  # 0: known from the first reply
        self.noise_shape = tuple(noise_shape or idr.get("noise_shape") or ())
        if self.server_takes_noise and not self.noise_shape:
            raise ValueError(
                "the policy server takes noise (metadata idr.noise) but says no noise_shape: set "
                "backbone.params.noise_shape=[T, D] (its action horizon and model action dim)"
            )

    # -- connection --------------------------------------------------------------------------
    def connect(self) -> None:
        from websockets.exceptions import WebSocketException
        from websockets.sync.client import connect

        self.close()
        uri = f"ws://{self.host}:{self.port}"
        deadline = time.monotonic() + self.timeout_s
        while True:  # a server restarting (refused) is waited for, up to timeout_s
            try:
                self._ws = connect(
                    uri,
                    open_timeout=max(0.1, deadline - time.monotonic()),
                    close_timeout=2,
                    max_size=self.max_reply_bytes,
                    compression=None,
                )
                first = self._ws.recv(timeout=max(0.1, deadline - time.monotonic()))
                break
            except (OSError, TimeoutError, WebSocketException) as e:
                self.close()
                error: Exception = e
                # refused, reset or closed while starting: a server restarting; try again
                if not isinstance(e, TimeoutError) and time.monotonic() + RECONNECT_S < deadline:
                    time.sleep(RECONNECT_S)
                    continue
            raise RemoteBackboneError(
                f"policy server {uri} (backbone.params.host/port): {type(error).__name__}: "
                f"{error} (waited {self.timeout_s:g} s: backbone.params.timeout_s)"
            )
        meta = self._decode(first, "its metadata")
        if not isinstance(meta, dict):
            raise RemoteBackboneError(f"policy server {uri} sent {type(meta).__name__} as metadata")
        self.metadata = meta

    def close(self) -> None:
        ws, self._ws = self._ws, None
        if ws is not None:
            try:
                ws.close()
            except Exception as e:  # closing anyway
                log.debug("closing the policy connection: %s", e)

    def _decode(self, frame: Any, what: str) -> Any:
        if isinstance(frame, str):  # the protocol's error form: the server's traceback
            raise RemoteBackboneError(f"the policy server failed on {what}:\n{frame[-3000:]}")
        try:
            return codec.unpackb(frame)
        except Exception as e:
            raise RemoteBackboneError(
                f"the policy server's reply to {what} is not msgpack: {e}"
            ) from None

    def _request(self, obs: dict[str, Any]) -> dict[str, Any]:
        from websockets.exceptions import WebSocketException

        if self._ws is None:
            self.connect()
        try:
            self._ws.send(codec.packb(obs))
            frame = self._ws.recv(timeout=self.timeout_s)
        except (OSError, TimeoutError, WebSocketException) as e:
            self.close()  # the next call connects anew
            big = "too big" in str(e)
            raise RemoteBackboneError(
                f"policy server ws://{self.host}:{self.port}: {type(e).__name__}: {e}"
                + (
                    f" (more than backbone.params.max_reply_bytes={self.max_reply_bytes})"
                    if big
                    else ""
                )
            ) from None
        reply = self._decode(frame, "an observation")
        if not isinstance(reply, dict) or "actions" not in reply:
            keys = sorted(reply) if isinstance(reply, dict) else type(reply).__name__
            raise RemoteBackboneError(f"the policy server's reply has no 'actions' (got {keys})")
        return reply

    # -- Backbone protocol -------------------------------------------------------------------
    def reset(self) -> None:
        """openpi's servers keep no episode state between requests."""

    def make_noise(self, batch_size: int, seed: int) -> np.ndarray | None:
        if not self.server_takes_noise:
            return None
        rng = np.random.default_rng(seed)
        return rng.standard_normal((batch_size, *self.noise_shape)).astype(np.float32)

    def _row(self, obs: Observation, i: int) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for ours, theirs in self.key_map.items():
            if ours == "prompt":
                out[theirs] = obs.instruction[i]
            elif ours == "state":
                s = obs.state[i]
                out[theirs] = (
                    s.detach().cpu().numpy() if hasattr(s, "detach") else np.asarray(s)
                ).astype(np.float32)
            else:
                out[theirs] = _to_uint8_hwc(obs.images[ours.split(":", 1)[1]][i])
        return out

    def predict_chunk(
        self, obs: Observation, noise: Any | None = None, intervention: Any | None = None
    ) -> np.ndarray:
        if intervention is not None:
            raise ValueError(f"{self.name} applies no interventions itself (raw space only)")
        b = obs.batch_size
        rows = [self._row(obs, i) for i in range(b)]
        if noise is not None and self.server_takes_noise:
            for i, row in enumerate(rows):
                row["noise"] = np.asarray(noise[i], dtype=np.float32)
        if self.server_batches and b > 1:
            batch = {
                k: [r[k] for r in rows]
                if k == self.key_map.get("prompt")
                else np.stack([r[k] for r in rows])
                for k in rows[0]
            }
            actions = np.asarray(self._request(batch)["actions"], dtype=np.float32)
            if actions.ndim != 3 or actions.shape[0] != b:
                raise RemoteBackboneError(
                    f"the policy server answered a batch of {b} with actions {actions.shape}; "
                    "expected (B, T, D)"
                )
        else:
            chunks = [np.asarray(self._request(r)["actions"], dtype=np.float32) for r in rows]
            if any(c.ndim != 2 for c in chunks):
                raise RemoteBackboneError(
                    f"the policy server answered actions {chunks[0].shape}; expected (T, D)"
                )
            actions = np.stack(chunks)
        if self.declared_action_dim and actions.shape[2] != self.declared_action_dim:
            raise RemoteBackboneError(
                f"the policy server answered {actions.shape[2]}-d actions but declared "
                f"{self.declared_action_dim} (its metadata action_dim, or backbone.params.action_dim)"
            )
        if self.chunk_len == 0:  # known from the first reply
            self.chunk_len, self.action_dim = actions.shape[1], actions.shape[2]
        return actions

    @classmethod
    def describe(cls, params: Mapping[str, Any]) -> PolicyIO | None:
        """What the server declares (its metadata's ``action_dim`` / ``action_horizon``, or
        these params), for the pre-flight's check against the env; None when it declares no
        action dim (the first reply is then checked)."""
        probe = cls(**{**params, "timeout_s": min(float(params.get("timeout_s", 30.0)), 10.0)})
        probe.close()
        if not probe.declared_action_dim:
            return None
        return PolicyIO(
            images={},  # the server resizes what it gets; the key map names the cameras
            state_dim=None,
            action_dim=probe.declared_action_dim,
            chunk_len=probe.chunk_len or 1,
            resizes_images=True,
            source=f"the policy server ws://{probe.host}:{probe.port}",
            declares_inputs=False,
        )

    @classmethod
    def dry_run(cls, params: Mapping[str, Any], env: EnvIO) -> None:
        """One request shaped like the env's observation (zeros, its cameras at their sizes,
        its state dim); the reply's actions must be (T, env.action_dim)."""
        import torch

        probe = cls(**{**params, "timeout_s": min(float(params.get("timeout_s", 30.0)), 10.0)})
        try:
            missing = [c for c in probe.cameras if c not in env.cameras]
            if missing:
                raise ValueError(
                    f"backbone.params.key_map sends cameras {missing} the env does not render "
                    f"(env cameras: {list(env.cameras)})"
                )
            obs = Observation(
                images={c: torch.zeros(1, 3, *env.hw_of(c)) for c in probe.cameras},
                state=torch.zeros(1, env.state_dim),
                instruction=["dry run"],
            )
            try:
                actions = probe.predict_chunk(obs, probe.make_noise(1, 0))
            except RemoteBackboneError as e:
                raise ValueError(f"dry run on an observation shaped like the env's: {e}") from None
            if actions.shape[2] != env.action_dim:
                raise ValueError(
                    f"action: the env takes {env.action_dim}-d actions, but the policy server "
                    f"ws://{probe.host}:{probe.port} answered a dry run with actions "
                    f"{tuple(actions.shape[1:])} (T, D)"
                )
        finally:
            probe.close()

    @classmethod
    def check_params(cls, params: Mapping[str, Any]) -> None:
        """The pre-flight: connect once, read the metadata (an unreachable server is one error
        within ``timeout_s``)."""
        try:
            probe = cls(**{**params, "timeout_s": min(float(params.get("timeout_s", 30.0)), 10.0)})
        except RemoteBackboneError as e:
            raise ValueError(str(e)) from None
        probe.close()
