"""Executors: where episodes run, under the scheduler's retry and dedup policy.

An executor owns its workers' lifecycle: it starts them, hands each a spec, kills and replaces
one that dies, runs out of memory or overruns ``executor.episode_timeout_s``, and reports each
episode as an :class:`Outcome`. It never retries and never writes: the scheduler decides what
an outcome means. Two exist:

- :class:`~pipeline.execution.executors.inline.InlineExecutor`: one EpisodeWorker in this process
  (debugging, tests; SIGALRM for timeouts);
- :class:`~pipeline.execution.executors.ray_pool.RayActorPool`: N Ray actors, local or on a cluster.

Env servers and a shared policy service plug in below this layer: a worker may hold an env
proxy or a policy client instead of the simulator or the model, and the executor is unchanged.
"""

from __future__ import annotations

from pipeline.execution.executors.base import Executor, ExecutorStats, Outcome
from pipeline.planning.config import ExecutorConfig
from workers.episode.rows import WorkerSpec

__all__ = ["Executor", "ExecutorStats", "Outcome", "make_executor"]


def make_executor(worker_spec: WorkerSpec, ex: ExecutorConfig) -> Executor:
    if ex.kind == "inline":
        from pipeline.execution.executors.inline import InlineExecutor

        return InlineExecutor(worker_spec, ex.episode_timeout_s)
    from pipeline.execution.executors.ray_pool import RayActorPool

    return RayActorPool(worker_spec, ex)
