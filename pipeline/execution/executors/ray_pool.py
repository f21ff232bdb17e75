"""A pool of Ray actors, each an EpisodeWorker, on a local Ray or a cluster.

One episode per actor at a time: when an actor dies, the episode it was running is the only
one charged an attempt (queued calls would die with it, innocent). Episodes last seconds and a
call round trip ~1 ms, so queueing more would gain nothing.

An actor that dies under an episode (``RayActorError``: a crash, a kill, its node lost), runs
out of memory or overruns ``episode_timeout_s`` is killed and replaced. A replacement's
episode clock starts once it has loaded; while it waits for capacity that may never come back
(a lost node), its episode is handed back to the started actors after ``REQUEUE_AFTER_S``.
"""

from __future__ import annotations

import logging
import re
import time
from dataclasses import dataclass, replace
from typing import Any

from pipeline.errors import RunError
from pipeline.execution.executors.base import ExecutorStats, Outcome
from pipeline.execution.timeouts import timeout_reason
from pipeline.planning.config import ExecutorConfig
from pipeline.planning.executor_config import SharedExecutor
from workers.episode.rows import EpisodeSpec, WorkerSpec

log = logging.getLogger("idr_eval.executors.ray")
STARTUP_TIMEOUT_S = 600  # an actor that has not loaded by then is taken as never starting
# a replacement that has not started by then (its node lost, no capacity left) hands its
# queued episode to a started actor; it still gets work if it starts later
REQUEUE_AFTER_S = 30.0


def log_socket_stats(i: int, st: dict[str, int]) -> None:
    """A policy actor's socket: connections taken and requests answered, and every refusal by
    kind (a peer without the run's token, over the cap, an oversized or malformed frame), a
    warning when there were any."""
    if not st:
        return
    refused = {k: v for k, v in st.items() if k not in ("accepted", "answered", "active") and v}
    line = (
        f"policy actor {i} socket: {st.get('accepted', 0)} connections, "
        f"{st.get('answered', 0)} requests answered"
    )
    if refused:
        kinds = ", ".join(f"{k} {v}" for k, v in sorted(refused.items()))
        log.warning("%s; refused or closed: %s", line, kinds)
    else:
        log.info("%s; none refused", line)


def load_error(exc: BaseException) -> str | None:
    """The error an actor's constructor raised (a checkpoint that cannot load, a simulator that
    cannot start), as its last traceback line; None for a death of another kind (a kill)."""
    if not getattr(exc, "actor_init_failed", False):
        return None
    lines = [ln.strip() for ln in re.sub(r"\x1b\[[0-9;]*m", "", str(exc)).splitlines()]
    found = [ln for ln in lines if re.match(r"^[\w.]+(Error|Exception|Exit)\b.*:", ln)]
    return found[-1] if found else lines[-1] if lines else type(exc).__name__


@dataclass
class _Call:
    actor_id: int
    spec: EpisodeSpec
    began: float | None  # when the episode's clock started (None: its actor is still loading)


class RayActorPool:
    def __init__(self, worker_spec: WorkerSpec, ex: ExecutorConfig) -> None:
        self.worker_spec = worker_spec
        self.ex = ex
        self.stats = ExecutorStats()
        self.actors: dict[int, Any] = {}  # live view, for tests and diagnostics
        self._busy: dict[int, int] = {}  # actor id -> episodes it holds (0 or 1)
        self._starting: dict[int, tuple[Any, float]] = {}  # replacements: ping ref, since
        self._calls: dict[Any, _Call] = {}  # object ref -> the call it answers
        self._next_id = 0
        self._cls: Any = None
        self.policy_actors: list[Any] = []  # shared policy: the actors holding the backbone

    # -- lifecycle ----------------------------------------------------------------------------
    def _spawn(self, replacement: bool = False) -> int:
        if self._cls is None:
            from workers.episode.worker import remote_worker_class

            ex = self.ex
            demand = ex.actor_demand()
            self._cls = remote_worker_class(
                demand["CPU"], demand["GPU"], ex.resources, ex.placement, ex.episodes_per_actor()
            )
        self._next_id += 1
        aid = self._next_id
        spec = self.worker_spec
        if self.policy_actors:  # episode actors spread over the policy actors
            spec = replace(spec, policy_actor=self.policy_actors[aid % len(self.policy_actors)])
        self.actors[aid] = self._cls.remote(spec)
        self._busy[aid] = 0
        if replacement:
            self._starting[aid] = (self.actors[aid].ping.remote(), time.monotonic())
        return aid

    def _kill(self, aid: int) -> None:
        import ray

        actor = self.actors.pop(aid, None)
        self._busy.pop(aid, None)
        self._starting.pop(aid, None)
        if actor is not None:
            try:
                ray.kill(actor, no_restart=True)
            except Exception as exc:
                log.warning("could not kill an actor: %s", exc)

    def _replace(self, aid: int) -> None:
        if aid in self.actors:
            self._kill(aid)
            self._spawn(replacement=True)
            self.stats.replaced += 1

    def start(self, n_pending: int) -> None:
        """Start min(workers, n_pending) actors and wait until each has loaded; an actor that
        dies while loading is replaced up to ``max_attempts`` times."""
        import ray
        from ray.exceptions import GetTimeoutError, RayActorError, WorkerCrashedError

        if self.actors or n_pending == 0:
            return
        t0 = time.monotonic()
        if isinstance(self.ex, SharedExecutor):
            self._start_policy_actors(self.ex)
        load_errors: set[str] = set()
        for _ in range(min(self.ex.workers, n_pending)):
            self._spawn()
        for aid in list(self.actors):
            for attempt in range(1, self.ex.max_attempts + 1):
                try:
                    worker = ray.get(self.actors[aid].ping.remote(), timeout=STARTUP_TIMEOUT_S)
                    self.stats.workers.append(worker)
                    break
                except GetTimeoutError:
                    raise RuntimeError(
                        f"actors did not start within {STARTUP_TIMEOUT_S} s: the cluster lacks "
                        f"the resources asked for ({self._demand()})"
                    ) from None
                except (RayActorError, WorkerCrashedError) as exc:
                    why = load_error(exc)
                    if why is not None and why in load_errors:  # the same error twice: final
                        raise RunError(
                            f"the workers cannot load: {why} (raised twice in an actor's "
                            "constructor; fix it and run the same command again)"
                        ) from None
                    load_errors.add(why or "")
                    if attempt == self.ex.max_attempts:
                        raise RunError(
                            f"actors keep dying while starting ({why or type(exc).__name__}); "
                            f"last: {str(exc).splitlines()[0]}"
                        ) from None
                    log.warning(
                        "actor %d died while starting, replacing it: %s",
                        aid,
                        why or type(exc).__name__,
                    )
                    self._kill(aid)
                    aid = self._spawn()
                    self.stats.replaced += 1
        self.stats.startup_seconds = time.monotonic() - t0

    def _start_policy_actors(self, ex: SharedExecutor) -> None:
        """The backbone's actors of a shared policy, loaded before any episode actor."""
        import ray
        from ray.exceptions import RayActorError

        from workers.policy.actor import policy_actor_class

        spec = self.worker_spec
        cls = policy_actor_class(ex.policy_cpus, ex.gpu_share)
        self.policy_actors = [
            cls.remote(
                spec.backbone_kind,
                spec.backbone_params,
                spec.batched,
                ex.max_batch,
                ex.batch_wait_ms,
                log_dir=spec.log_dir,
                rows=spec.forward_rows,
                threads=spec.torch_threads,
                env=spec.numerics_env,
                transport=ex.policy_transport,
                socket_settings=spec.policy_socket,
            )
            for _ in range(ex.policy_actors)
        ]
        try:
            infos = ray.get(
                [a.describe.remote() for a in self.policy_actors], timeout=STARTUP_TIMEOUT_S
            )
        except RayActorError as exc:
            raise RunError(
                f"the policy actors cannot load: {load_error(exc) or type(exc).__name__}"
            ) from None
        log.info("policy actors: numerical path %s", infos[0]["numerics"])
        for info in infos:
            self.stats.workers.append(f"policy {info['worker']}")
            if not info["batched"]:
                log.warning(
                    "backbone %s cannot batch: the policy actors run each request's three "
                    "passes in turn (no batching across episodes)",
                    info["name"],
                )

    def close(self) -> None:
        import ray

        for aid in list(self.actors):  # also on SIGTERM / an error: no actor outlives the run
            self._kill(aid)
        self._calls.clear()
        if self.policy_actors:
            try:
                for i, st in enumerate(
                    ray.get([a.stats.remote() for a in self.policy_actors], timeout=5)
                ):
                    log.info(
                        "policy actor %d: %d requests in %d forwards (mean batch %.1f), busy "
                        "%.1f s, %d forwards split for lack of device memory%s",
                        i,
                        st["requests"],
                        st["forwards"],
                        st["mean_batch"],
                        st["busy_s"],
                        st["oom_splits"],
                        f" (now at most {st['fit']} requests per forward)" if st["fit"] else "",
                    )
                    log_socket_stats(i, st.get("socket") or {})
            except Exception as exc:  # closing anyway
                log.debug("no policy actor stats: %s", exc)
        for actor in self.policy_actors:
            try:
                ray.kill(actor, no_restart=True)
            except Exception as exc:
                log.warning("could not kill a policy actor: %s", exc)
        self.policy_actors = []

    def _demand(self) -> str:
        return f"{self.ex.cpus_per_worker} CPU, {self.ex.gpu_share:g} GPU per worker"

    # -- dispatch -----------------------------------------------------------------------------
    def _idle(self) -> list[int]:
        """Actors that may take an episode now, least loaded first. A replacement still
        loading gets work only while no started actor is left: after a node is lost, its
        replacement may wait for capacity that never comes back."""
        any_started = any(a not in self._starting for a in self._busy)
        per_actor = self.ex.episodes_per_actor()
        return [
            a
            for a in sorted(self._busy, key=self._busy.get)
            if self._busy[a] < per_actor and not (any_started and a in self._starting)
        ]

    def free_slots(self) -> int:
        per_actor = self.ex.episodes_per_actor()
        cap = self.ex.max_in_flight or len(self._busy) * per_actor
        free = sum(per_actor - self._busy[a] for a in self._idle())
        return max(0, min(free, cap - len(self._calls)))

    def in_flight(self) -> int:
        return len(self._calls)

    def submit(self, spec: EpisodeSpec) -> None:
        idle = self._idle()
        if not idle or self.free_slots() == 0:
            raise RuntimeError("RayActorPool.submit: no free actor (wait for an outcome first)")
        aid = idle[0]
        ref = self.actors[aid].run_episode.remote(spec)
        began = None if aid in self._starting else time.monotonic()
        self._calls[ref] = _Call(aid, spec, began)
        self._busy[aid] += 1

    def wait(self, timeout_s: float) -> list[Outcome]:
        import ray
        from ray.exceptions import NodeDiedError, RayActorError, WorkerCrashedError

        out: list[Outcome] = []
        if self._calls:
            ready, _ = ray.wait(list(self._calls), num_returns=1, timeout=timeout_s)
        else:
            ready = []
        for ref in ready:
            call = self._calls.pop(ref)
            if call.actor_id in self._busy:
                self._busy[call.actor_id] -= 1
            try:
                result = ray.get(ref)
            except (RayActorError, WorkerCrashedError, NodeDiedError) as exc:
                log.warning("actor %d died under %s: replacing it", call.actor_id, call.spec.key)
                self._replace(call.actor_id)
                reason = f"{type(exc).__name__}: actor died during the episode"
                out.append(Outcome(call.spec, lost=reason))
                continue
            if result.unhealthy:
                log.warning(
                    "actor %d ran out of memory under %s: replacing it",
                    call.actor_id,
                    call.spec.key,
                )
                self._replace(call.actor_id)
            out.append(Outcome(call.spec, result=result))
        out.extend(self._watch_starting())
        out.extend(self._cut_off_overruns())
        return out

    def _cut_off_overruns(self) -> list[Outcome]:
        limit = self.ex.episode_timeout_s
        if not limit:
            return []
        now, out = time.monotonic(), []
        for ref, call in list(self._calls.items()):
            if call.began is not None and now - call.began > limit:
                log.warning(
                    "episode %s timed out on actor %d: replacing it", call.spec.key, call.actor_id
                )
                del self._calls[ref]
                self.stats.timeouts += 1
                self._replace(call.actor_id)
                out.append(Outcome(call.spec, lost=timeout_reason(limit), timed_out=True))
        return out

    def _watch_starting(self) -> list[Outcome]:
        """Start the episode clock of replacements that finished loading; hand the episodes of
        one that waits for capacity (a lost node) back, to go to a started actor."""
        if not self._starting:
            return []
        import ray

        pings = {ping: aid for aid, (ping, _) in self._starting.items()}
        done, _ = ray.wait(list(pings), num_returns=len(pings), timeout=0)
        now = time.monotonic()
        for ping in done:
            aid = pings[ping]
            del self._starting[aid]
            for call in self._calls.values():
                if call.actor_id == aid and call.began is None:
                    call.began = now
        any_started = any(a not in self._starting for a in self._busy)
        out: list[Outcome] = []
        for aid, (_, since) in list(self._starting.items()):
            held = [ref for ref, c in self._calls.items() if c.actor_id == aid]
            if any_started and held and now - since > REQUEUE_AFTER_S:
                log.warning(
                    "replacement actor %d has waited %.0f s for resources (a node lost?): its "
                    "episode goes to a started actor",
                    aid,
                    now - since,
                )
                for ref in held:  # not charged an attempt: it never began
                    call = self._calls.pop(ref)
                    self._busy[aid] -= 1
                    out.append(Outcome(call.spec, requeue=True))
                    try:
                        ray.cancel(ref)
                    except Exception as exc:
                        log.debug("could not cancel a queued episode: %s", exc)
            elif held and now - since > STARTUP_TIMEOUT_S:
                raise RuntimeError(
                    f"a replacement actor did not start within {STARTUP_TIMEOUT_S} s ({self._demand()})"
                )
        return out
