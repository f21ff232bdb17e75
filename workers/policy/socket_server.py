"""The policy actor's own socket: requests of the shared policy service without a Ray call each.

Ray places a policy actor, restarts it when it dies and tells the episode workers where it is;
each inference then goes over a TCP connection of the episode's own to the actor, in the env
servers' frame format (``workers.envs.server.wire``: a 4-byte length and a msgpack map, arrays as
raw bytes). Measured on the 2-core box (``benchmarks/bench_serving.py``), a Ray actor call costs
1.3-1.8 ms more than a round trip on such a socket, for the same payload and the same forward.

The socket only carries: a request is answered by the actor's ``infer``, the same batcher and
forward as a Ray call's, so both transports give the same tables. Messages hold plain values
and arrays only (no pickle), so a peer can send nothing but data (``socket_messages``: what
travels; ``socket_settings``: the token, the limits, the endpoint; ``socket_client``: an
episode's connection).

Nothing on the network drives a run (docs/guarantees.md, "Ports and peers"):

- **A per-run secret.** A connection's first bytes are a fixed-size auth frame
  (``socket_settings.AUTH_FRAME_BYTES``: a magic and the run's ``SocketToken``), compared with
  ``hmac.compare_digest``. Until it has arrived whole a connection holds no thread and no more
  than that many bytes: one selector thread reads the auth frames of every new connection, at
  most ``max_pending`` at once (the oldest is dropped for a newer one) and each for
  ``auth_timeout_s``; a wrong or late frame closes the connection, nothing else read.
- **Bounded.** Connections past the auth frame each get a thread, at most ``max_connections``
  per server (the excess is closed at once); one idle for ``idle_timeout_s`` is closed (its
  client reconnects and sends the request again, as after an actor restart); a frame longer than
  ``max_frame`` (derived from the env's images and dims: ``socket_settings.frame_bound``) is
  refused on its length prefix; bytes are read as they arrive (the wire's frame rules).
- **Checked.** A frame that does not decode closes its connection; a message of the wrong shape
  (``socket_messages.check_request``) is answered with an error before it can reach a batch.

Each refusal is counted (:meth:`PolicySocketServer.stats`, in the run's log at its end) and the
first ones are logged with the peer's address; the token never is.
"""

from __future__ import annotations

import contextlib
import logging
import math
import selectors
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

from workers.envs.server import wire
from workers.policy.service import InferRequest
from workers.policy.socket_messages import request_from_message, step_message
from workers.policy.socket_settings import AUTH_FRAME_BYTES, SocketLimits, SocketToken
from workers.policy.wrapper import IDRStep

log = logging.getLogger(__name__)

Answer = Callable[[InferRequest, str | None], IDRStep]


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
            while self._serve_one(conn, peer):
                pass
        except Exception:  # never out of the thread; the connection is closed
            log.exception("policy socket %s:%d: serving %s failed", *self.address, peer)
        finally:
            self._live.pop(conn, None)
            self._idled.discard(conn)
            with self._lock:
                self._active -= 1
            # closed after its slot is free: a peer that sees the close may connect again at
            # once and must not find the cap still counting this connection
            conn.close()

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
