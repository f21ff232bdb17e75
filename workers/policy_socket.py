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

Nothing on the network drives a run (docs/guarantees.md, "Ports and peers"):

- **A per-run secret.** A connection's first bytes are a fixed-size auth frame
  (:data:`AUTH_FRAME_BYTES`: a magic and the run's :class:`SocketToken`), compared with
  ``hmac.compare_digest``. Until it has arrived whole a connection holds no thread and no more
  than that many bytes: one selector thread reads the auth frames of every new connection, at
  most ``max_pending`` at once (the oldest is dropped for a newer one) and each for
  ``auth_timeout_s``; a wrong or late frame closes the connection, nothing else read.
- **Bounded.** Connections past the auth frame each get a thread, at most ``max_connections``
  per server (the excess is closed at once); one idle for ``idle_timeout_s`` is closed (its
  client reconnects and sends the request again, as after an actor restart); a frame longer than
  ``max_frame`` (derived from the env's images and dims: :func:`frame_bound`) is refused on its
  length prefix; bytes are read as they arrive (the wire's frame rules).
- **Checked.** A frame that does not decode closes its connection; a message of the wrong shape
  (:func:`check_request`) is answered with an error before it can reach a batch.

Each refusal is counted (:meth:`PolicySocketServer.stats`, in the run's log at its end) and the
first ones are logged with the peer's address; the token never is.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hmac
import logging
import math
import secrets
import selectors
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from idr_core.interventions import InterventionConfig
from idr_core.refiner import Diagnostics, RefinerConfig

from workers.backbones.base import Observation
from workers.envs.server import wire
from workers.idr_wrapper import IDRStep
from workers.policy_service import InferRequest

if TYPE_CHECKING:
    from workers.io_spec import EnvIO

log = logging.getLogger(__name__)

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


# -- the server -------------------------------------------------------------------------------
#: refusals logged one by one (with the peer's address) per kind; beyond, only counted
LOGGED_REFUSALS = 10


class PolicySocketServer:
    """Listens on ``host`` (a free port): one selector thread takes connections and their auth
    frames; each authenticated connection is answered in a thread of its own, with ``answer``
    (the policy actor's ``infer``). Refusals are counted in :meth:`stats`."""

    def __init__(
        self,
        answer: Answer,
        host: str,
        token: SocketToken,
        limits: SocketLimits = SocketLimits(),
    ) -> None:
        self._answer = answer
        self._token = token
        self.limits = limits
        self._sock = socket.create_server((host, 0), backlog=256)
        self._sock.setblocking(False)
        self.address: tuple[str, int] = self._sock.getsockname()[:2]
        self._wake_r, self._wake_w = socket.socketpair()  # close() wakes the selector
        self._lock = threading.Lock()
        self._counts: Counter[str] = Counter()
        self._active = 0
        # authenticated connections -> when they were last heard from (inf: being answered);
        # the selector thread closes the idle ones (no timeout on each read: ~10 us a request)
        self._live: dict[socket.socket, float] = {}
        self._idled: set[socket.socket] = set()
        self._closed = False
        self._thread = threading.Thread(target=self._accept, name="policy-socket", daemon=True)
        self._thread.start()

    # -- accounting ----------------------------------------------------------------------------
    def _count(self, kind: str, peer: Any = None) -> None:
        with self._lock:
            self._counts[kind] += 1
            n = self._counts[kind]
        if kind != "accepted" and kind != "answered" and n <= LOGGED_REFUSALS:
            more = " (further ones counted only)" if n == LOGGED_REFUSALS else ""
            log.warning("policy socket %s:%d: %s, peer %s%s", *self.address, kind, peer, more)

    def stats(self) -> dict[str, int]:
        """Connections and frames by outcome: ``accepted`` (authenticated), ``answered``
        (requests), and the refusals: ``bad_token``, ``auth_timeout``, ``auth_evicted``
        (dropped for a newer one), ``over_cap``, ``oversized``, ``malformed``,
        ``bad_request`` (answered with an error), ``idle_closed``; ``active`` now."""
        with self._lock:
            return {**self._counts, "active": self._active}

    def refusals(self) -> int:
        st = self.stats()
        return sum(v for k, v in st.items() if k not in ("accepted", "answered", "active"))

    # -- accepting -----------------------------------------------------------------------------
    def _accept(self) -> None:
        """New connections and their auth frames, without a thread or a buffer of their own
        beyond :data:`AUTH_FRAME_BYTES`; the rest of a connection is ``_serve``'s."""
        sel = selectors.DefaultSelector()
        sel.register(self._sock, selectors.EVENT_READ, "listen")
        sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        pending: dict[socket.socket, tuple[float, bytearray, Any]] = {}  # oldest first

        def drop(conn: socket.socket, kind: str | None) -> None:
            _, _, peer = pending.pop(conn)
            sel.unregister(conn)
            if kind is not None:  # counted before the peer can see the close
                self._count(kind, peer)
            conn.close()

        reap_every = min(1.0, self.limits.idle_timeout_s / 4)
        next_reap = time.monotonic() + reap_every
        try:
            while not self._closed:
                now = time.monotonic()
                wait = min((d for d, _, _ in pending.values()), default=next_reap) - now
                for key, _ in sel.select(max(0.0, min(wait, next_reap - now))):
                    if key.data == "wake":
                        return
                    if key.data == "listen":
                        self._take(sel, pending, drop)
                        continue
                    conn = key.fileobj
                    assert isinstance(conn, socket.socket)
                    if conn in pending:
                        self._read_auth(conn, sel, pending, drop)
                now = time.monotonic()
                for conn in [c for c, (d, _, _) in pending.items() if d <= now]:
                    drop(conn, "auth_timeout")
                if now >= next_reap:
                    self._reap(now)
                    next_reap = now + reap_every
        except Exception:  # never out of the thread: the socket just stops taking connections
            log.exception("policy socket %s:%d: the accept loop failed", *self.address)
        finally:
            for conn in list(pending):
                drop(conn, None)
            sel.close()

    def _reap(self, now: float) -> None:
        """Shut the connections idle for longer than ``idle_timeout_s`` (their threads see the
        end of the stream and count them)."""
        for conn, seen in list(self._live.items()):
            if now - seen > self.limits.idle_timeout_s and conn not in self._idled:
                self._idled.add(conn)
                with contextlib.suppress(OSError):
                    conn.shutdown(socket.SHUT_RDWR)

    def _take(self, sel: selectors.BaseSelector, pending: dict, drop: Callable) -> None:
        try:
            conn, peer = self._sock.accept()
        except (BlockingIOError, InterruptedError):
            return
        except OSError:  # out of file descriptors, or closed: try again on the next event
            time.sleep(0.01)
            return
        if len(pending) >= self.limits.max_pending:
            drop(next(iter(pending)), "auth_evicted")
        conn.setblocking(False)
        pending[conn] = (time.monotonic() + self.limits.auth_timeout_s, bytearray(), peer)
        sel.register(conn, selectors.EVENT_READ, "auth")

    def _read_auth(
        self,
        conn: socket.socket,
        sel: selectors.BaseSelector,
        pending: dict,
        drop: Callable,
    ) -> None:
        _, buf, peer = pending[conn]
        try:
            data = conn.recv(AUTH_FRAME_BYTES - len(buf))  # nothing past the auth frame
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            drop(conn, "bad_token")
            return
        if not data:
            drop(conn, "bad_token")  # closed before the whole auth frame
            return
        buf += data
        if len(buf) < AUTH_FRAME_BYTES:
            return
        pending.pop(conn)
        sel.unregister(conn)
        if not self._token.accepts(buf):
            self._count("bad_token", peer)
            conn.close()
            return
        with self._lock:
            admitted = self._active < self.limits.max_connections
            self._active += admitted
        if not admitted:
            self._count("over_cap", peer)
            conn.close()
            return
        self._count("accepted")
        conn.setblocking(True)
        self._live[conn] = time.monotonic()
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        threading.Thread(target=self._serve, args=(conn, peer), daemon=True).start()

    # -- serving -------------------------------------------------------------------------------
    def _serve(self, conn: socket.socket, peer: Any) -> None:
        try:
            with conn:
                while self._serve_one(conn, peer):
                    pass
        except Exception:  # never out of the thread; the connection is closed
            log.exception("policy socket %s:%d: serving %s failed", *self.address, peer)
        finally:
            self._live.pop(conn, None)
            self._idled.discard(conn)
            with self._lock:
                self._active -= 1

    def _serve_one(self, conn: socket.socket, peer: Any) -> bool:
        """One request and its reply; False when the connection is done."""
        try:
            msg = wire.recv(conn, self.limits.max_frame)
        except wire.FrameTooLarge:
            self._count("oversized", peer)
            return False
        except wire.MalformedFrame:
            self._count("malformed", peer)
            return False
        except (wire.WireError, OSError):
            if conn in self._idled:  # shut by the selector thread (_reap)
                self._count("idle_closed", peer)
            return False  # the client is done (or gone)
        self._live[conn] = math.inf  # being answered: not idle, however long the forward
        try:
            request, client = request_from_message(msg)
        except Exception as exc:  # not a request: its error alone, nothing reaches a batch
            self._count("bad_request", peer)
            return self._reply(conn, _error_reply(exc))
        try:
            reply: dict[str, Any] = {
                "ok": True,
                "step": step_message(self._answer(request, client)),
            }
        except Exception as exc:  # the request's error travels back; the connection stays
            reply = _error_reply(exc)
        self._count("answered")
        return self._reply(conn, reply)

    def _reply(self, conn: socket.socket, reply: dict[str, Any]) -> bool:
        self._live[conn] = time.monotonic()
        try:
            wire.send(conn, reply)
        except TypeError as exc:  # an answer msgpack cannot carry: said instead
            wire.send(conn, _error_reply(exc))
        except OSError:
            return False
        return True

    def close(self) -> None:
        """Stop listening (the selector thread is woken; authenticated connections end when
        their clients close them or go idle)."""
        self._closed = True
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")
        self._thread.join(timeout=5)
        with contextlib.suppress(OSError):  # already shut down, or never connected
            self._sock.shutdown(socket.SHUT_RDWR)
        self._sock.close()
        self._wake_r.close()
        self._wake_w.close()


def _error_reply(exc: BaseException) -> dict[str, Any]:
    return {"ok": False, "type": type(exc).__name__, "message": str(exc)}


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


def node_address() -> str:
    """The address this node is reached at by the other Ray nodes (127.0.0.1 outside Ray)."""
    try:
        import ray

        return ray.util.get_node_ip_address()
    except Exception:  # no Ray here: a local caller
        return "127.0.0.1"
