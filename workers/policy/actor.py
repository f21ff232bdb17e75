"""The shared policy service on Ray: policy actors that batch many episodes' requests, and the
simulator side's proxy to them.

A policy actor (a threaded Ray actor around :class:`workers.policy.service.PolicyWorker`)
queues requests as they arrive; a batcher thread takes the first one waiting, gathers more for
up to ``batch_wait_ms`` or until ``max_batch``, and runs one forward, while requests keep
queueing, so the next batch starts at once. It stops gathering early once every client it has
heard from recently has a request in the batch: a client is one closed loop (an episode thread
that waits for its answer before it asks again), so no further request can come, and waiting
out ``batch_wait_ms`` would only delay the forward. A lone client's request, with nothing
queued and no forward running, is run in the Ray thread that received it: no hand-off to the
batcher and back (two thread wake-ups), the same forward. Ray restarts a policy
actor that dies (``max_restarts``) and retries the calls it held (``max_task_retries``): a
request is a pure function of its content, so a retry gives the same answer.

:class:`PolicyServiceClient` is what an episode worker holds instead of an ``IDRWrapper`` in shared
mode: the same ``reset`` / ``infer`` (each inference with its cell), one request per inference (never per env
step), the observation sent once as numpy: over a connection of its own to the actor's socket
(``workers.policy.socket_server``, ``executor.policy_transport=socket``) or as a Ray call (``ray``).
"""

from __future__ import annotations

import queue
import threading
import time
from typing import Any, Literal

import numpy as np
from idr_core.interventions import InterventionConfig
from idr_core.refiner import RefinerConfig
from idr_core.tensors import is_torch

from workers.backbones.base import Observation
from workers.policy.service import InferRequest, PolicyWorker
from workers.policy.socket_client import PolicyServiceError, PolicySocketConnection
from workers.policy.socket_server import PolicySocketServer
from workers.policy.socket_settings import RAY_CALLS, PolicyEndpoint, SocketSettings, SocketToken
from workers.policy.wrapper import IDRStep


class BatchingPolicyActor:
    """The policy actor's body (Ray wraps it with ``policy_actor_class``). Each ``infer`` call
    runs in one of Ray's threads (a threaded actor: a Ray call to an asyncio actor cost ~3.7 ms
    more on the 2-core box) and waits while one batcher thread runs the forwards."""

    def __init__(
        self,
        kind: str,
        params: dict[str, Any],
        batched: bool | None,
        max_batch: int,
        batch_wait_ms: float,
        log_dir: str | None = None,
        rows: int | str | None = None,
        threads: int | None = None,
        env: dict[str, str] | None = None,
        transport: Literal["socket", "ray"] = "socket",
        socket_settings: SocketSettings | None = None,
    ) -> None:
        from workers.hardware import apply_numerics_env
        from workers.worker_log import log_to_file

        log_to_file(log_dir, "policy")  # its output in the run dir, not on the terminal
        apply_numerics_env(env or {})  # before the backbone loads (executor.numerics_mode)
        self.worker = PolicyWorker(kind, params, batched, rows, threads)
        self.max_batch = max_batch
        self.wait_s = batch_wait_ms / 1e3
        self._queue: queue.SimpleQueue[_Pending] = queue.SimpleQueue()
        self._last_seen: dict[str, float] = {}  # client -> monotonic time of its last request
        self._batch_sizes: list[int] = []
        self._served: list[float] = []
        self._busy_s = 0.0
        # one forward at a time: the batcher's, or a lone client's run in its own Ray thread
        self._forward = threading.Lock()
        threading.Thread(target=self._batcher, name="batcher", daemon=True).start()
        self._socket: PolicySocketServer | None = None
        if transport == "socket":  # outside a run (a benchmark, a test): loopback, a new token
            settings = socket_settings or SocketSettings("127.0.0.1", None)
            self._token = settings.token or SocketToken.new()
            self._socket = PolicySocketServer(
                self.infer, settings.bind_host(), self._token, settings.limits
            )

    def describe(self) -> dict[str, Any]:
        """What the actor serves (the backbone's description) and where it runs."""
        import os
        import socket

        return {**self.worker.describe(), "worker": f"{socket.gethostname()}:{os.getpid()}"}

    def endpoint(self) -> PolicyEndpoint:
        """Where episode workers send requests (workers.policy.socket_server): the socket's address
        now (a restarted actor listens on another port), or Ray calls. The token reaches them
        over Ray's own (authenticated) calls, never a log line."""
        if self._socket is None:
            return RAY_CALLS
        return PolicyEndpoint(
            "socket", self._socket.address, self._token, self._socket.limits.max_frame
        )

    def stats(self) -> dict[str, Any]:
        sizes = list(self._batch_sizes)
        return {
            # connections and frames by outcome (refusals among them), for the run's log
            "socket": self._socket.stats() if self._socket is not None else {},
            "forwards": len(sizes),
            "requests": sum(sizes),
            "mean_batch": float(np.mean(sizes)) if sizes else 0.0,
            "busy_s": self._busy_s,
            "served_ms_median": float(np.median(self._served)) * 1e3 if self._served else 0.0,
            "oom_splits": self.worker.splits,
            "fit": self.worker.fit or 0,
        }

    def infer(self, request: InferRequest, client: str | None = None) -> IDRStep:
        """One request; ``client`` names its closed loop (one request at a time), None for a
        caller that does not say (the batch then waits out ``batch_wait_ms``)."""
        t_in = time.perf_counter()
        pending = _Pending(request, client)
        if client is not None:
            self._last_seen[client] = time.monotonic()
            if self._clients([pending]) == 1 and self._forward.acquire(blocking=False):
                try:  # the only client, nothing queued, no forward running: run it here
                    if self._queue.empty():
                        self._run([pending])
                finally:
                    self._forward.release()
        if not pending.done.is_set():
            self._queue.put(pending)
        pending.done.wait()
        if pending.error is not None:
            raise pending.error
        assert pending.answer is not None
        self._served.append(time.perf_counter() - t_in)
        return pending.answer

    def _clients(self, batch: list[_Pending]) -> int:
        """How many requests this batch can still expect: the clients heard from within
        ``CLIENT_ACTIVE_S``, or ``max_batch`` when a request in it names no client."""
        if any(p.client is None for p in batch):
            return self.max_batch
        since = time.monotonic() - CLIENT_ACTIVE_S
        for client, seen in list(self._last_seen.items()):
            if seen < since:  # finished, or gone: no longer waited for
                self._last_seen.pop(client, None)
        return max(1, len(self._last_seen))

    def _batcher(self) -> None:
        while True:
            batch = [self._queue.get()]
            deadline = time.monotonic() + self.wait_s
            while len(batch) < min(self.max_batch, self._clients(batch)):
                left = deadline - time.monotonic()
                try:
                    batch.append(
                        self._queue.get(timeout=left) if left > 0 else self._queue.get_nowait()
                    )
                except queue.Empty:
                    break
            with self._forward:
                self._run(batch)

    def _run(self, batch: list[_Pending]) -> None:
        """One forward of ``batch`` (the caller holds ``_forward``); each request gets its answer
        or its error. A forward that fails as a whole is run again per request, so a request
        that cannot be answered (a peer's odd but well-formed one) fails alone: with a fixed
        forward shape each of its mates gets the answer it gets in any batch."""
        t0 = time.perf_counter()
        try:  # a forward out of memory is split (PolicyWorker): errors are per request
            answers = self.worker.infer_each([p.request for p in batch])
        except Exception as exc:
            answers = [exc] if len(batch) == 1 else [self._alone(p.request) for p in batch]
        finally:
            self._busy_s += time.perf_counter() - t0
        self._batch_sizes.append(len(batch))
        for p, answer in zip(batch, answers, strict=True):
            if isinstance(answer, BaseException):
                p.error = answer
            else:
                p.answer = answer
            p.done.set()

    def _alone(self, request: InferRequest) -> IDRStep | BaseException:
        try:
            return self.worker.infer_each([request])[0]
        except Exception as exc:
            return exc


#: times a request is sent again over a new connection to a policy actor that went away (or
#: that closed it at its connection cap: a burst of other connections holds every slot)
RECONNECTS = 10

#: the wait before a reconnect doubles from this, up to RECONNECT_WAIT_MAX_S (about 8 s over
#: all reconnects): a cap filled for a moment frees before the tries run out
RECONNECT_WAIT_S = 0.02
RECONNECT_WAIT_MAX_S = 2.0

#: a client silent for longer (an episode worker done, or gone) is no longer waited for
CLIENT_ACTIVE_S = 5.0


class _Pending:
    """A request waiting for its forward."""

    __slots__ = ("answer", "client", "done", "error", "request")

    def __init__(self, request: InferRequest, client: str | None) -> None:
        self.request = request
        self.client = client
        self.done = threading.Event()
        self.answer: IDRStep | None = None
        self.error: BaseException | None = None


MAX_WAITING = 256  # episodes one policy actor serves at once (more wait in Ray's queue)


def policy_actor_class(
    num_cpus: float, num_gpus: float, resources: dict[str, float] | None = None
) -> Any:
    """The Ray actor class of a policy actor (Ray imported here, lazily)."""
    import ray

    return ray.remote(
        num_cpus=num_cpus,
        num_gpus=num_gpus,
        resources=dict(resources) if resources else None,
        max_restarts=-1,  # a policy actor that dies is started again...
        max_task_retries=-1,  # ...and the requests it held are sent to it again
        max_concurrency=MAX_WAITING,  # requests waiting at once, each in a thread of Ray's
    )(BatchingPolicyActor)


def _plain(value: Any) -> Any:
    if is_torch(value):
        return value.detach().cpu().numpy()
    return value


def _image_bytes(image: Any) -> Any:
    """An image in [0, 1] as the uint8 it was made from (a quarter of the bytes), when it was
    made from one exactly (``workers.episode.observation.image_to_tensor``); else as it is. The
    policy side divides by 255 again: the same floats."""
    x = _plain(image)
    if isinstance(x, np.ndarray) and x.dtype == np.float32:
        u8 = np.rint(x * 255).clip(0, 255).astype(np.uint8)
        if np.array_equal(u8.astype(np.float32) / np.float32(255), x):
            return u8
    return x


class PolicyServiceClient:
    """The IDRWrapper interface over a policy actor (see the module docstring): ``handle`` (a
    Ray handle; None outside Ray), ``endpoint`` (where requests go), ``info`` (the actor's
    ``describe``: what it serves)."""

    def __init__(
        self,
        handle: Any,
        endpoint: PolicyEndpoint,
        info: dict[str, Any] | None = None,
        cfg: RefinerConfig | None = None,
        intervention: InterventionConfig | None = None,
    ) -> None:
        import uuid

        self.handle = handle
        self.endpoint = endpoint
        self.info = dict(info or {})
        self._id = uuid.uuid4().hex[:12]
        # what a request without settings of its own carries (benchmarks, tests)
        self.cfg = cfg or RefinerConfig()
        self.intervention = intervention or InterventionConfig()
        self.batched = bool(self.info.get("batched"))
        self._local = threading.local()  # each thread (closed loop) its own connection

    def reset(self) -> None:
        """Nothing to forget: the service calls the backbone on whole chunks, without state."""

    def finish(self, action: Any) -> Any:
        """The base's steps after its unnormalizer, on an averaged action (temporal
        ensembling): none for a base without them; refused for one with them."""
        if self.info.get("finishes_chunks"):
            raise ValueError(
                f"mode 'temporal' with the shared policy service: the base {self.info['name']!r} "
                "post-processes chunks after its unnormalizer, which must run after the "
                "averaging; run it with executor.policy: in_actor"
            )
        return action

    def infer(
        self,
        obs: Observation,
        step_seed: int = 0,
        cfg: RefinerConfig | None = None,
        intervention: InterventionConfig | None = None,
    ) -> IDRStep:
        request = self.request(obs, step_seed, cfg, intervention)
        if self.endpoint.transport == "socket":
            return self._infer_on_socket(request)
        import ray

        return ray.get(self.handle.infer.remote(request, self.client_id))

    def _infer_on_socket(self, request: InferRequest) -> IDRStep:
        """The request over this thread's connection to the policy actor. A connection that
        breaks means the actor died: Ray starts it again (``max_restarts``), ``describe`` (a
        Ray call, retried until it is back) says where it listens now, and the request is sent
        again (a pure function of its content: the same answer), as Ray retries a call. The
        tries are spaced (doubling waits): an actor at its connection cap closes a new
        connection at once, and a burst that fills the cap for a moment must not use them all."""
        for attempt in range(RECONNECTS + 1):
            try:
                return self._connection().infer(request, self.client_id)
            except OSError as exc:  # refused, reset, or wire.WireError (a ConnectionError)
                self._drop_connection()
                if attempt == RECONNECTS or self.handle is None:
                    raise PolicyServiceError(
                        f"the policy actor at {self.endpoint.address} cannot be reached "
                        f"({type(exc).__name__}: {exc}) after {attempt + 1} tries"
                    ) from exc
                import ray

                time.sleep(min(RECONNECT_WAIT_MAX_S, RECONNECT_WAIT_S * 2**attempt))
                self.endpoint = ray.get(self.handle.endpoint.remote())
        raise AssertionError("unreachable")

    def _connection(self) -> PolicySocketConnection:
        conn = getattr(self._local, "conn", None)
        if conn is None:
            endpoint = self.endpoint
            assert endpoint.address is not None and endpoint.token is not None  # a socket's
            conn = self._local.conn = PolicySocketConnection(
                endpoint.address, endpoint.token, endpoint.max_frame
            )
        return conn

    def _drop_connection(self) -> None:
        conn = getattr(self._local, "conn", None)
        self._local.conn = None
        if conn is not None:
            conn.close()

    def close(self) -> None:
        """Close this thread's connection (the actor's thread for it ends)."""
        self._drop_connection()

    @property
    def client_id(self) -> str:
        """This caller's closed loop: the client and the thread asking (an episode worker may
        run several episodes, each in a thread of its own, through one client)."""
        return f"{self._id}:{threading.get_ident()}"

    def request(
        self,
        obs: Observation,
        step_seed: int = 0,
        cfg: RefinerConfig | None = None,
        intervention: InterventionConfig | None = None,
    ) -> InferRequest:
        """What ``infer`` sends: the observation as plain numpy (images as the uint8 they were
        made from), the step seed and the inference's cell (``cfg``, ``intervention``; None:
        the client's defaults)."""
        extras = dict(obs.extras)
        if "privileged" in extras:  # lazy views of the live simulator: sent as plain dicts
            extras["privileged"] = [None if p is None else dict(p) for p in extras["privileged"]]
        plain = Observation(
            images={k: _image_bytes(v) for k, v in obs.images.items()},
            state=_plain(obs.state),
            instruction=list(obs.instruction),
            do_image=obs.do_image,
            do_state=obs.do_state,
            extras=extras,
        )
        return InferRequest(
            plain, int(step_seed), cfg or self.cfg, intervention or self.intervention
        )


def connect(handle: Any, cfg: RefinerConfig | None = None) -> PolicyServiceClient:
    """A client of the policy actor ``handle``: what it serves and where it listens, asked
    over Ray (a restarting actor is waited for); ``cfg``: what a request without settings of
    its own carries."""
    import ray

    info, endpoint = ray.get([handle.describe.remote(), handle.endpoint.remote()])
    return PolicyServiceClient(handle, endpoint, info, cfg)
