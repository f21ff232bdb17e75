"""An episode's connection to its policy actor's socket: one closed loop (a request, then its
answer), opened with the run's auth frame (``workers.policy.socket_settings``); the messages are
``workers.policy.socket_messages``.
"""

from __future__ import annotations

import socket

from workers.envs.server import wire
from workers.policy.service import InferRequest
from workers.policy.socket_messages import request_message, step_from_message
from workers.policy.socket_settings import DEFAULT_MAX_FRAME, SocketToken
from workers.policy.wrapper import IDRStep


class PolicyServiceError(RuntimeError):
    """A request the policy actor answered with an error (its type and message), or a policy
    actor that cannot be reached."""


class PolicySocketConnection:
    """One client's connection (one closed loop: a request, then its answer); its first bytes
    are the run's auth frame."""

    def __init__(
        self,
        address: tuple[str, int],
        token: SocketToken,
        max_frame: int = DEFAULT_MAX_FRAME,
        timeout_s: float = 10.0,
    ) -> None:
        self.address = address
        self.max_frame = max_frame
        self._sock = socket.create_connection(address, timeout=timeout_s)
        self._sock.settimeout(None)  # a forward may take long; a dead peer closes the socket
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._sock.sendall(token.auth_frame())

    def infer(self, request: InferRequest, client: str | None) -> IDRStep:
        wire.send(self._sock, request_message(request, client))
        reply = wire.recv(self._sock, self.max_frame)
        if not isinstance(reply, dict) or not isinstance(reply.get("ok"), bool):
            raise PolicyServiceError(f"the policy actor answered {type(reply).__name__}")
        if not reply["ok"]:
            raise PolicyServiceError(f"{reply.get('type')}: {reply.get('message')}")
        return step_from_message(reply["step"])

    def close(self) -> None:
        self._sock.close()
