"""The scheduler: episode specs -> actors -> results -> store.

Every cell sees the same tasks, episode indices, seeds and so init states, so comparisons
between cells are paired. Executor ``ray`` starts N actors (local ``ray.init(num_cpus=...)``
or an existing cluster by address) and dispatches with ``ray.wait`` under a cap on the work
in flight; ``inline`` runs one worker in this process, without Ray, for debugging.

Faults: a dead actor is replaced and its episodes re-queued; an exception inside an episode
comes back as an error row and is retried; after ``max_attempts`` the last error row is
stored (never counted as a task failure). An episode past ``executor.episode_timeout_s`` has
its actor killed and replaced (inline: SIGALRM, see pipeline.timeouts), and so has an actor
that ran out of memory. Results are handed to the store as they finish, in small batches; a
key already stored is dropped, so a call that Ray ran twice is stored once.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pipeline import signals
from pipeline.config import ExecutorConfig
from pipeline.signals import critical_section
from pipeline.store import RunStore
from pipeline.timeouts import EpisodeTimeout, alarm, alarm_supported, timeout_reason
from workers.episode import EpisodeResult, EpisodeSpec, WorkerSpec

log = logging.getLogger("idr_eval.scheduler")
STARTUP_TIMEOUT_S = 600  # an actor that has not loaded by then is taken as never starting
# a replacement that has not started by then (its node lost, no capacity left) hands its
# queued episode to a started actor; it still gets work if it starts later
REQUEUE_AFTER_S = 30.0


@dataclass
class RunSummary:
    total: int
    skipped: int = 0  # already stored (resume)
    stored: int = 0
    successes: int = 0
    errors: int = 0  # keys stored as error rows after max_attempts
    retries: int = 0
    actors_replaced: int = 0
    timeouts: int = 0  # episodes cut off at executor.episode_timeout_s
    duplicates_dropped: int = 0
    wall_seconds: float = 0.0
    startup_seconds: float = 0.0  # until the workers were ready (actors started, models loaded)
    workers: list[str] = field(default_factory=list)


class _Progress:
    """done/total, success so far, ETA: a live bar on a terminal, log lines otherwise."""

    def __init__(self, total: int) -> None:
        self.total, self.t0, self._last = total, time.monotonic(), 0.0
        self._bar = None
        if total and sys.stderr.isatty():
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self._bar = Progress(
                TextColumn("[bold]episodes"),
                BarColumn(),
                TextColumn("{task.completed}/{task.total}"),
                TextColumn("{task.fields[info]}"),
                TimeRemainingColumn(),
            )
            self._task = self._bar.add_task("run", total=total, info="")
            self._bar.start()

    def update(self, done: int, successes: int, errors: int) -> None:
        info = f"success {successes}/{max(done - errors, 0)}  errors {errors}"
        if self._bar is not None:
            self._bar.update(self._task, completed=done, info=info)
            return
        now = time.monotonic()
        if now - self._last >= 5.0 or done == self.total:
            self._last = now
            rate = done / max(now - self.t0, 1e-9)
            eta = (self.total - done) / rate if rate > 0 else float("nan")
            log.info("episodes %d/%d  %s  eta %.0fs", done, self.total, info, eta)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()


class Scheduler:
    def __init__(
        self,
        worker_spec: WorkerSpec,
        specs: list[EpisodeSpec],
        store: RunStore,
        executor: ExecutorConfig,
        on_flush: Callable[[list[EpisodeResult]], None] | None = None,
        deferred: Callable[[], list[EpisodeSpec]] | None = None,
        deferred_total: int = 0,
    ) -> None:
        """``deferred``: called once every spec so far is stored (e.g. after tau calibration)
        for the episodes of a later stage; ``deferred_total`` is their count, for progress."""
        self.worker_spec = worker_spec
        self.store = store
        self.ex = executor
        self.on_flush = on_flush
        done = store.stored_keys()
        self.pending = deque(s for s in specs if s.key not in done)
        self.summary = RunSummary(
            total=len(specs) + deferred_total, skipped=len(specs) - len(self.pending)
        )
        self._deferred = deferred
        self._stored_keys = done
        self._buffer: list[EpisodeResult] = []
        self._progress: _Progress | None = None
        self.actors: dict[int, Any] = {}

    # -- result handling (shared by both executors) --------------------------------------
    def _accept(self, spec: EpisodeSpec, result: EpisodeResult) -> None:
        if result.key in self._stored_keys or any(r.key == result.key for r in self._buffer):
            self.summary.duplicates_dropped += 1
            return
        if result.is_error and spec.attempt < self.ex.max_attempts:
            self.summary.retries += 1
            log.warning(
                "episode %s attempt %d failed, retrying: %s",
                spec.key,
                spec.attempt,
                result.episode["error"].splitlines()[0],
            )
            self.pending.append(spec.retry())
            return
        self._buffer.append(result)
        self.summary.errors += int(result.is_error)
        self.summary.successes += int(bool(result.episode["success"]) and not result.is_error)
        if len(self._buffer) >= self.ex.flush_every:
            self.flush()

    def _fail_without_result(self, spec: EpisodeSpec, reason: str) -> None:
        """The actor died under this episode: retry, or store an error row at the last attempt."""
        if spec.attempt < self.ex.max_attempts:
            log.warning(
                "episode %s attempt %d failed, retrying: %s", spec.key, spec.attempt, reason
            )
            self.summary.retries += 1
            self.pending.append(spec.retry())
            return
        row = spec.row_head(self.worker_spec.backbone_kind, self.worker_spec.env_suite)
        row["error"] = reason
        self._accept(spec, EpisodeResult(row, []))

    def flush(self) -> None:
        if not self._buffer:
            return
        with critical_section():  # a SIGTERM waits until the batch is written and recorded
            batch, self._buffer = self._buffer, []
            self.store.write(batch)
            self._stored_keys.update(r.key for r in batch)
            self.summary.stored += len(batch)
        if self.on_flush is not None:
            self.on_flush(batch)

    def _take_deferred(self) -> bool:
        """Start the next stage once everything before it is stored; False when none is left."""
        if self._deferred is None:
            return False
        self.flush()
        later, self._deferred = self._deferred(), None
        fresh = [s for s in later if s.key not in self._stored_keys]
        self.summary.skipped += len(later) - len(fresh)
        self.pending.extend(fresh)
        return bool(fresh) or self._deferred is not None

    def _tick(self) -> None:
        if self._progress is not None:
            s = self.summary
            self._progress.update(s.skipped + s.stored + len(self._buffer), s.successes, s.errors)

    # -- executors ------------------------------------------------------------------------------
    def run(self) -> RunSummary:
        t0 = time.monotonic()
        self._progress = _Progress(self.summary.total)
        try:
            if not self.pending:
                self._take_deferred()
            if self.pending:
                self._run_inline() if self.ex.kind == "inline" else self._run_ray()
        finally:
            self.flush()
            self._tick()
            self._progress.close()
            self.summary.wall_seconds = time.monotonic() - t0
        return self.summary

    def _run_inline(self) -> None:
        from workers.actor import EpisodeWorker

        t0 = time.monotonic()
        worker = EpisodeWorker(self.worker_spec)
        self.summary.workers = [worker.ping()]
        self.summary.startup_seconds = time.monotonic() - t0
        limit = self.ex.episode_timeout_s
        if limit and not alarm_supported():
            log.warning(
                "executor.episode_timeout_s=%g is not enforced: the inline executor needs the "
                "main thread for SIGALRM (use executor.kind=ray)",
                limit,
            )
        try:
            while self.pending or self._take_deferred():
                spec = self.pending.popleft()
                try:
                    with alarm(limit):
                        result = worker.run_episode(spec)
                except EpisodeTimeout:
                    log.warning("episode %s timed out: replacing the worker", spec.key)
                    self.summary.timeouts += 1
                    worker = self._replace_inline(worker)
                    self._fail_without_result(spec, timeout_reason(limit or 0))
                    continue
                self._accept(spec, result)
                if result.unhealthy:
                    worker = self._replace_inline(worker)
                self._tick()
        finally:
            worker.close()

    def _replace_inline(self, worker: Any) -> Any:
        """A fresh EpisodeWorker (the old one may be mid-step or out of memory)."""
        from workers.actor import EpisodeWorker

        try:
            worker.close()
        except Exception as exc:  # a broken worker may fail to close; it is dropped anyway
            log.warning("closing the old worker failed: %s", exc)
        self.summary.actors_replaced += 1
        return EpisodeWorker(self.worker_spec)

    def _run_ray(self) -> None:
        import ray

        from workers.actor import remote_worker_class

        cls = remote_worker_class(
            self.ex.cpus_per_worker, self.ex.gpu_share, self.ex.resources, self.ex.placement
        )
        actors: dict[int, Any] = {}
        self.actors = actors  # live view, for tests and diagnostics
        # replacements still loading (ping ref, since when): their episode's clock waits
        starting: dict[int, tuple[Any, float]] = {}
        next_id = 0

        def start(replacement: bool = False) -> int:
            nonlocal next_id
            next_id += 1
            actors[next_id] = cls.remote(self.worker_spec)
            if replacement:
                starting[next_id] = (actors[next_id].ping.remote(), time.monotonic())
            return next_id

        try:
            self._start_actors(actors, start)
            self._dispatch(actors, starting, start)
        finally:  # also on SIGTERM / an error: no actor outlives the run
            for a in actors.values():
                try:
                    ray.kill(a, no_restart=True)
                except Exception as exc:
                    log.warning("could not kill an actor: %s", exc)

    def _start_actors(self, actors: dict[int, Any], start: Callable[..., int]) -> None:
        import ray
        from ray.exceptions import GetTimeoutError, RayActorError, WorkerCrashedError

        t0 = time.monotonic()
        for _ in range(min(self.ex.workers, len(self.pending))):
            start()
        self.summary.workers = []
        for aid in list(actors):
            for attempt in range(1, self.ex.max_attempts + 1):
                try:
                    self.summary.workers.append(
                        ray.get(actors[aid].ping.remote(), timeout=STARTUP_TIMEOUT_S)
                    )
                    break
                except GetTimeoutError:
                    raise RuntimeError(
                        f"actors did not start within {STARTUP_TIMEOUT_S} s: the cluster lacks the "
                        f"resources asked for ({self.ex.cpus_per_worker} CPU, "
                        f"{self.ex.gpu_share:g} GPU per worker)"
                    ) from None
                except (RayActorError, WorkerCrashedError) as exc:
                    # an actor that dies while loading (OOM, a crashing simulator) is replaced
                    if attempt == self.ex.max_attempts:
                        raise RuntimeError(f"actors keep dying while starting: {exc}") from None
                    log.warning(
                        "actor %d died while starting, replacing it: %s", aid, type(exc).__name__
                    )
                    ray.kill(actors.pop(aid), no_restart=True)
                    aid = start()
                    self.summary.actors_replaced += 1
        self.summary.startup_seconds = time.monotonic() - t0

    def _dispatch(
        self,
        actors: dict[int, Any],
        starting: dict[int, tuple[Any, float]],
        start: Callable[..., int],
    ) -> None:
        import ray
        from ray.exceptions import NodeDiedError, RayActorError, WorkerCrashedError

        # One episode per actor at a time: when an actor dies, the episode it was running is
        # the only one charged an attempt (queued calls would die with it, innocent). Episodes
        # last seconds and a call round trip ~1 ms, so queueing more would gain nothing.
        cap = self.ex.max_in_flight or len(actors)
        limit = self.ex.episode_timeout_s
        in_flight: dict[Any, tuple[int, EpisodeSpec]] = {}
        clock: dict[Any, float | None] = {}  # ref -> when its episode started (None: not yet)
        load = dict.fromkeys(actors, 0)

        def replace(aid: int) -> None:
            if aid in actors:
                ray.kill(actors.pop(aid), no_restart=True)
                load.pop(aid, None)
                starting.pop(aid, None)
                load[start(replacement=True)] = 0
                self.summary.actors_replaced += 1

        while self.pending or in_flight or (not in_flight and self._take_deferred()):
            # A replacement still loading gets work only while no started actor is left: after
            # a node is lost, its replacement may wait for capacity that never comes back.
            started = any(a not in starting for a in load)
            for aid in sorted(load, key=load.get):
                if started and aid in starting:
                    continue
                if self.pending and load[aid] == 0 and len(in_flight) < cap:
                    spec = self.pending.popleft()
                    ref = actors[aid].run_episode.remote(spec)
                    in_flight[ref] = (aid, spec)
                    clock[ref] = None if aid in starting else time.monotonic()
                    load[aid] += 1
            ready, _ = ray.wait(list(in_flight), num_returns=1, timeout=1.0)
            for ref in ready:
                aid, spec = in_flight.pop(ref)
                clock.pop(ref, None)
                if aid in load:
                    load[aid] -= 1
                try:
                    result = ray.get(ref)
                except (RayActorError, WorkerCrashedError, NodeDiedError) as exc:
                    reason = f"{type(exc).__name__}: actor died during the episode"
                    log.warning("actor %d died under %s: replacing it", aid, spec.key)
                    replace(aid)
                    self._fail_without_result(spec, reason)
                    continue
                self._accept(spec, result)
                if result.unhealthy:
                    log.warning("actor %d ran out of memory under %s: replacing it", aid, spec.key)
                    replace(aid)
            self._watch_starting(starting, in_flight, clock, load)
            if limit:
                now = time.monotonic()
                for ref, (aid, spec) in list(in_flight.items()):
                    began = clock.get(ref)
                    if began is not None and now - began > limit:
                        log.warning("episode %s timed out on actor %d: replacing it", spec.key, aid)
                        del in_flight[ref], clock[ref]
                        self.summary.timeouts += 1
                        replace(aid)
                        self._fail_without_result(spec, timeout_reason(limit))
            self._tick()

    def _watch_starting(
        self,
        starting: dict[int, tuple[Any, float]],
        in_flight: dict[Any, tuple[int, EpisodeSpec]],
        clock: dict[Any, float | None],
        load: dict[int, int] | None = None,
    ) -> None:
        """Start the episode clock of replacement actors that finished loading; hand the
        episodes of one that waits for capacity (a lost node) to the started actors."""
        if not starting:
            return
        import ray

        pings = {ping: aid for aid, (ping, _) in starting.items()}
        done, _ = ray.wait(list(pings), num_returns=len(pings), timeout=0)
        now = time.monotonic()
        for ping in done:
            aid = pings[ping]
            del starting[aid]
            for ref, (a, _) in in_flight.items():
                if a == aid and clock.get(ref) is None:
                    clock[ref] = now
        started = load is not None and any(a not in starting for a in load)
        for aid, (_, since) in starting.items():
            held = [ref for ref, (a, _) in in_flight.items() if a == aid]
            if started and held and now - since > REQUEUE_AFTER_S:
                log.warning(
                    "replacement actor %d has waited %.0f s for resources (a node lost?): its "
                    "episode goes to a started actor",
                    aid,
                    now - since,
                )
                for ref in held:  # not charged an attempt: it never began
                    _, spec = in_flight.pop(ref)
                    clock.pop(ref, None)
                    load[aid] -= 1
                    self.pending.appendleft(spec)
                    try:
                        ray.cancel(ref)
                    except Exception as exc:
                        log.debug("could not cancel a queued episode: %s", exc)
            elif held and now - since > STARTUP_TIMEOUT_S:
                raise RuntimeError(
                    f"a replacement actor did not start within {STARTUP_TIMEOUT_S} s "
                    f"({self.ex.cpus_per_worker} CPU, {self.ex.gpu_share:g} GPU per worker)"
                )


def init_ray(
    address: str | None,
    num_cpus: float | None,
    num_gpus: float | None = None,
    resources: dict[str, float] | None = None,
) -> None:
    """Connect to a cluster (``address``) or start a local one with ``num_cpus`` (and custom
    ``resources``). ``pipeline.cluster.connect`` probes the address and checks capacity first."""
    import ray

    if ray.is_initialized():
        return
    env = {"RAY_DEDUP_LOGS": "1"}
    for k, v in env.items():
        os.environ.setdefault(k, v)
    if address:
        ray.init(address=address, log_to_driver=True)
    else:
        ray.init(
            num_cpus=num_cpus,
            num_gpus=num_gpus,
            resources=resources,
            include_dashboard=False,
            log_to_driver=True,
        )
    signals.reinstall()  # ray.init replaced our SIGTERM handler with one that aborts
