"""The policy actor's own socket: requests of the shared policy service without a Ray call each.

Ray places a policy actor, restarts it when it dies and tells the episode workers where it is;
each inference then goes over a TCP connection of the episode's own to the actor, in the env
servers' frame format (``workers.envs.server.wire``: a 4-byte length and a msgpack map, arrays as
raw bytes). Measured on the 2-core box (``benchmarks/bench_serving.py``), a Ray actor call costs
1.3-1.8 ms more than a round trip on such a socket, for the same payload and the same forward.

The socket only carries: a request is answered by the actor's ``infer``, the same batcher and
forward as a Ray call's, so both transports give the same tables. Messages hold plain values
and arrays only (no pickle), so a peer can send nothing but data.

A request is one flat map (``client``, ``seed``, ``idr``, ``intervention`` and the observation's
fields: ``request_message``); replies ``{"ok": True, "step": ...}`` or
``{"ok": False, "type": exception class name, "message": ...}``.
"""

from __future__ import annotations

import contextlib
import dataclasses
import socket
import threading
from collections.abc import Callable
from typing import Any

from workers.backbones.base import Observation
from workers.envs.server import wire
from workers.idr import Diagnostics, RefinerConfig
from workers.idr_wrapper import IDRStep
from workers.interventions import InterventionConfig
from workers.policy_service import InferRequest

Answer = Callable[[InferRequest, str | None], IDRStep]


class PolicyServiceError(RuntimeError):
    """A request the policy actor answered with an error (its type and message), or a policy
    actor that cannot be reached."""


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


class PolicySocketServer:
    """Listens on ``host`` (a free port) and answers each connection's requests in a thread of
    its own, with ``answer`` (the policy actor's ``infer``)."""

    def __init__(self, answer: Answer, host: str) -> None:
        self._answer = answer
        self._sock = socket.create_server((host, 0), backlog=256)
        self.address: tuple[str, int] = self._sock.getsockname()[:2]
        threading.Thread(target=self._accept, name="policy-socket", daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self._sock.accept()
            except OSError:  # closed
                return
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            threading.Thread(target=self._serve, args=(conn,), daemon=True).start()

    def _serve(self, conn: socket.socket) -> None:
        with conn:
            while True:
                try:
                    msg = wire.recv(conn)
                except (wire.WireError, OSError):
                    return  # the client is done (or gone)
                try:
                    request, client = request_from_message(msg)
                    reply: dict[str, Any] = {
                        "ok": True,
                        "step": step_message(self._answer(request, client)),
                    }
                except Exception as exc:  # the request's error travels back; the connection stays
                    reply = {"ok": False, "type": type(exc).__name__, "message": str(exc)}
                try:
                    wire.send(conn, reply)
                except OSError:
                    return

    def close(self) -> None:
        """Stop listening (a thread blocked in ``accept`` is woken by the shutdown, not by
        ``close`` alone)."""
        with contextlib.suppress(OSError):  # already shut down, or never connected
            self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()


class PolicySocketConnection:
    """One client's connection (one closed loop: a request, then its answer)."""

    def __init__(self, address: tuple[str, int], timeout_s: float = 10.0) -> None:
        self.address = address
        self._sock = socket.create_connection(address, timeout=timeout_s)
        self._sock.settimeout(None)  # a forward may take long; a dead peer closes the socket
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def infer(self, request: InferRequest, client: str | None) -> IDRStep:
        wire.send(self._sock, request_message(request, client))
        reply = wire.recv(self._sock)
        if not reply["ok"]:
            raise PolicyServiceError(f"{reply['type']}: {reply['message']}")
        return step_from_message(reply["step"])

    def close(self) -> None:
        self._sock.close()


def node_address() -> str:
    """The address this node is reached at by the other Ray nodes (127.0.0.1 outside Ray)."""
    try:
        import ray

        return ray.util.get_node_ip_address()
    except Exception:  # no Ray here: a local caller
        return "127.0.0.1"
