"""What a run sets for its policy sockets, as plain values (no socket opened): the run's secret
(:class:`SocketToken`, whose auth frame opens every connection), the bounds of a socket
(:func:`frame_bound`, :class:`SocketLimits`), where the sockets listen (:class:`SocketSettings`)
and how an episode reaches its policy actor (:class:`PolicyEndpoint`). The driver builds them
(``pipeline.execution.runner``); the server (``workers.policy.socket_server``) and the client
(``workers.policy.socket_client``) read them.
"""

from __future__ import annotations

import dataclasses
import hmac
import secrets
from typing import TYPE_CHECKING, Literal

if TYPE_CHECKING:
    from workers.io_spec import EnvIO


# -- the run's secret -------------------------------------------------------------------------
TOKEN_BYTES = 32
AUTH_MAGIC = b"IDRPOL01"  # names the protocol and its version: a stray client fails at once
AUTH_FRAME_BYTES = len(AUTH_MAGIC) + TOKEN_BYTES  # 40: the fixed-size first frame


class SocketToken:
    """The run's secret for its policy sockets (``pipeline.rundir.policy_token`` keeps it in the
    run dir, mode 0600). Its repr and str never show it: a token in a log line, an error message
    or a pretty-printer's dump reads ``SocketToken(...)`` (a plain class, not a dataclass, so
    that no printer walks its fields)."""

    __slots__ = ("_secret",)

    def __init__(self, secret: bytes) -> None:
        if not isinstance(secret, bytes) or len(secret) != TOKEN_BYTES:
            raise ValueError(f"a policy socket token is {TOKEN_BYTES} bytes")
        self._secret = secret

    def __eq__(self, other: object) -> bool:
        return isinstance(other, SocketToken) and hmac.compare_digest(self._secret, other._secret)

    def __hash__(self) -> int:
        return hash(self._secret)

    def __reduce__(self) -> tuple[type[SocketToken], tuple[bytes]]:  # over Ray's calls
        return (SocketToken, (self._secret,))

    @classmethod
    def new(cls) -> SocketToken:
        return cls(secrets.token_bytes(TOKEN_BYTES))

    @classmethod
    def from_hex(cls, text: str) -> SocketToken:
        return cls(bytes.fromhex(text.strip()))

    def hex(self) -> str:
        return self._secret.hex()

    def auth_frame(self) -> bytes:
        return AUTH_MAGIC + self._secret

    def accepts(self, frame: bytes) -> bool:
        """Whether ``frame`` is this token's auth frame (in constant time)."""
        return hmac.compare_digest(bytes(frame), self.auth_frame())

    def __repr__(self) -> str:
        return "SocketToken(...)"

    __str__ = __repr__


# -- bounds -----------------------------------------------------------------------------------
#: a run whose env declares no image sizes (no ``describe``): the frame bound
DEFAULT_MAX_FRAME = 64 << 20
#: what a request holds besides its arrays (instruction, configs, privileged extras), and a
#: reply besides its action chunks
FRAME_ALLOWANCE = 1 << 20
#: actions of the longest chunk a reply is sized for (four arrays of float64: the executed
#: chunk, the factual one and the two counterfactual ones)
MAX_CHUNK = 1024
HEADROOM = 2


def frame_bound(env: EnvIO | None) -> int:
    """The longest frame a run's policy socket accepts, from what its env renders and takes:
    every camera at its declared size as float32 (the widest an image travels; uint8 is a
    quarter), the state and an action chunk as float64, plus :data:`FRAME_ALLOWANCE`, times
    :data:`HEADROOM`. The env bounds it, not the policy: a policy that resizes accepts any size.
    None (an env that does not describe itself): :data:`DEFAULT_MAX_FRAME`."""
    if env is None:
        return DEFAULT_MAX_FRAME
    images = sum(3 * h * w * 4 for h, w in map(env.hw_of, env.cameras))
    state = env.state_dim * 8
    actions = 4 * MAX_CHUNK * env.action_dim * 8
    return HEADROOM * (images + max(state, actions) + FRAME_ALLOWANCE)


#: a connection silent for this long is closed, where the run sets no episode timeout: above the
#: longest gap between two inferences of an episode (an env server restarted under it, a slow
#: scene reset); a client whose connection was closed reconnects and sends again
DEFAULT_IDLE_S = 900.0


def connection_cap(episodes_in_flight: int) -> int:
    """Default connections per policy actor: twice the episodes that may talk to it at once
    (a replaced actor's connection lingers until the kernel or the idle timeout ends it) and a
    few more."""
    return 2 * episodes_in_flight + 8


@dataclasses.dataclass(frozen=True)
class SocketLimits:
    """What one policy socket holds at most (see the module docstring)."""

    max_frame: int = DEFAULT_MAX_FRAME  # bytes of one frame, either way (frame_bound)
    max_connections: int = 64  # authenticated connections at once; more are closed
    idle_timeout_s: float = DEFAULT_IDLE_S  # an authenticated connection silent this long
    auth_timeout_s: float = 5.0  # for the auth frame to arrive whole
    max_pending: int = 64  # connections waiting for their auth frame (the oldest dropped)

    def __post_init__(self) -> None:
        for name in ("max_frame", "max_connections", "max_pending"):
            if getattr(self, name) < 1:
                raise ValueError(f"SocketLimits.{name} must be >= 1")
        if not (self.idle_timeout_s > 0 and self.auth_timeout_s > 0):
            raise ValueError("SocketLimits: timeouts must be > 0")


@dataclasses.dataclass(frozen=True)
class SocketSettings:
    """A run's policy sockets: where they listen (None: the node's address, which the other
    nodes of a cluster reach; a local Ray gives 127.0.0.1), the run's token (None: a new one
    per policy actor, as outside a run; the runner sets the run's when the run starts), the
    limits."""

    host: str | None
    token: SocketToken | None
    limits: SocketLimits = SocketLimits()

    def bind_host(self) -> str:
        return self.host if self.host is not None else node_address()


@dataclasses.dataclass(frozen=True)
class PolicyEndpoint:
    """How an episode's requests reach its policy actor (``executor.policy_transport``), as the
    actor says over Ray (``BatchingPolicyActor.endpoint``). ``socket``: a connection to
    ``address`` opened with ``token``, frames up to ``max_frame`` bytes; ``ray``: a Ray call on
    the actor's handle (no address, no token). The token never shows in a repr."""

    transport: Literal["socket", "ray"]
    address: tuple[str, int] | None = None
    token: SocketToken | None = dataclasses.field(default=None, repr=False)
    max_frame: int = DEFAULT_MAX_FRAME

    def __post_init__(self) -> None:
        if self.transport not in ("socket", "ray"):
            raise ValueError(f"transport: 'socket' or 'ray', not {self.transport!r}")
        if self.transport == "socket" and (self.address is None or self.token is None):
            raise ValueError("a socket endpoint needs its address and the run's token")
        if self.transport == "ray" and (self.address is not None or self.token is not None):
            raise ValueError("a ray endpoint is the actor's handle: no address, no token")


#: requests as Ray calls on the actor's handle (``executor.policy_transport=ray``)
RAY_CALLS = PolicyEndpoint("ray")


def node_address() -> str:
    """The address this node is reached at by the other Ray nodes (127.0.0.1 outside Ray)."""
    try:
        import ray

        return ray.util.get_node_ip_address()
    except Exception:  # no Ray here: a local caller
        return "127.0.0.1"
