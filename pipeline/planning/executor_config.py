"""``executor``: where episodes run (Ray actors or inline), how many, with which resources, and
the policy's placement (in each actor, or a shared policy service).

The policy's placement decides what else the section holds, so the config's type says it: a
union of :class:`InActorExecutor` (each actor holds a backbone) and :class:`SharedExecutor` (policy
actors batch many episodes' requests: their number, CPUs, batch, wait, transport and socket
bounds), told apart by ``policy`` (``in_actor`` where it is absent). The YAML keys stay flat
(``executor.policy: shared``, ``executor.max_batch: 8``); a shared-only key given to an in_actor
run is refused with one message naming it, since that run would ignore it.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import BeforeValidator, Field, field_validator, model_validator

from pipeline.planning.config_model import StrictModel

PolicyPlacement = Literal["in_actor", "shared"]
Transport = Literal["socket", "ray"]

POLICY_DOC = (
    "in_actor: each actor holds a backbone and an env (the default; small policies, one "
    "machine); shared: actors hold only envs and send each inference to policy actors that batch "
    "many episodes' requests into one forward (a GPU per policy actor, or executor.actors_per_gpu "
    "of them per GPU); the same tables run to run (docs/reproducibility.md). The keys of the "
    "shared policy service (SharedExecutor's own) are refused with in_actor"
)


class ExecutorBase(StrictModel):
    """What both placements have (their methods are overridden where the shared one differs)."""

    kind: Literal["ray", "inline"] = "ray"
    workers: int = Field(default=2, ge=1, description="actors (each holds a backbone and an env)")
    cpus_per_worker: float = Field(default=1.0, gt=0)
    gpus_per_worker: float = Field(default=0.0, ge=0)
    address: str | None = Field(default=None, description="existing Ray cluster; None = local")
    max_in_flight: int | None = Field(
        default=None, ge=1, description="episodes running at once; None: one per worker"
    )
    max_attempts: int = Field(default=3, ge=1, description="tries per episode before giving up")
    oversubscribe: bool = Field(
        default=False, description="allow more local worker CPUs than this machine has"
    )
    flush_every: int = Field(default=8, ge=1, description="episodes per Parquet batch")
    episode_timeout_s: float | None = Field(
        default=None,
        gt=0,
        description="wall-clock limit per episode: a hung episode's actor is replaced and the "
        "episode retried (inline: SIGALRM, main thread only); None: no limit",
    )
    # -- where the model lives (each variant narrows it to its own value)
    policy: PolicyPlacement = Field(default="in_actor", description=POLICY_DOC)
    # -- the forward's shape (a row's float rounding depends on it: workers.policy.forward_shape)
    forward_rows: int | None = Field(
        default=None,
        ge=1,
        description="rows of every backbone forward (padded to it, or cut into forwards of it); "
        "None: shared, 3 x max_batch (one IDR request is 3 rows); in_actor, each inference's own "
        "rows (1, or 3 for IDR). The same value in both modes gives the same tables",
    )
    numerics_mode: Literal["native", "portable"] = Field(
        default="native",
        description="native: each host's own kernels (tables equal run to run on one machine); "
        "portable: torch, MKL and oneDNN pinned to AVX2 and llvmpipe to 256-bit vectors in "
        "every actor, so x86 machines of other CPU models give the same tables "
        "(docs/reproducibility.md)",
    )
    torch_threads: int | None = Field(
        default=None,
        ge=1,
        description="torch's CPU threads in every process holding a backbone (a CPU forward's "
        "float order depends on them); None: the CPUs it holds (policy_cpus shared, "
        "cpus_per_worker in_actor), at least 1",
    )
    # -- placement on a cluster (pipeline.execution.cluster checks it against the nodes before any work)
    actors_per_gpu: int | None = Field(
        default=None,
        ge=1,
        description="actors sharing one GPU: each asks for 1/n of a GPU (instead of "
        "gpus_per_worker); None: gpus_per_worker decides",
    )
    resources: dict[str, float] = Field(
        default_factory=dict,
        description="custom Ray resources per actor, e.g. {node_type_gpu: 0.01} to pin actors "
        "to nodes started with --resources (a local run declares them on its one node)",
    )
    placement: Literal["default", "spread"] = Field(
        default="default",
        description="spread: actors on as many nodes as possible (Ray's SPREAD strategy); "
        "default: Ray's (fill a node, then the next)",
    )
    autoscaling: bool = Field(
        default=False,
        description="the cluster adds nodes on demand (Ray autoscaler, KubeRay): do not refuse "
        "a run that the nodes up now cannot hold",
    )

    @field_validator("resources")
    @classmethod
    def _custom_resources(cls, v: dict[str, float]) -> dict[str, float]:
        for name, amount in v.items():
            if name in ("CPU", "GPU", "memory", "object_store_memory"):
                raise ValueError(
                    f"{name!r} is not a custom resource: use cpus_per_worker / gpus_per_worker / "
                    "actors_per_gpu"
                )
            if not (amount > 0 and amount == amount and amount != float("inf")):
                raise ValueError(f"resources.{name}: must be a finite number > 0 (got {amount})")
        return v

    @model_validator(mode="after")
    def _one_gpu_setting(self) -> ExecutorBase:
        if self.actors_per_gpu is not None and self.gpus_per_worker not in (
            0,
            1 / self.actors_per_gpu,
        ):
            raise ValueError(
                f"actors_per_gpu={self.actors_per_gpu} and gpus_per_worker="
                f"{self.gpus_per_worker:g} disagree: set one of them"
            )
        return self

    def forward_shape(self) -> int | Literal["dynamic"] | None:
        """Rows of every forward (see ``forward_rows``); "dynamic"; None: each inference's own."""
        return self.forward_rows

    def threads(self) -> int:
        """torch threads of a process holding a backbone (see ``torch_threads``)."""
        return self.torch_threads or max(1, int(self.cpus_per_worker))

    def episodes_per_actor(self) -> int:
        """Episodes one (episode) actor runs at once: in_actor, one (its backbone serves one
        episode at a time)."""
        return 1

    @property
    def gpu_share(self) -> float:
        """GPUs asked for by one actor (fractional when actors share a GPU)."""
        return 1 / self.actors_per_gpu if self.actors_per_gpu else self.gpus_per_worker

    def actor_demand(self) -> dict[str, float]:
        """What one (episode) actor asks the cluster for, as Ray resource names."""
        return {"CPU": self.cpus_per_worker, "GPU": self.gpu_share, **self.resources}

    def actor_groups(self) -> list[tuple[str, int, dict[str, float]]]:
        """(what, how many, what each asks for) of every kind of actor the run starts, in the
        order they are placed."""
        return [("executor.workers", self.workers, self.actor_demand())]

    def local_cpus(self) -> float:
        """CPUs a local Ray is started with: every actor's."""
        return sum(n * d["CPU"] for _, n, d in self.actor_groups())


class SharedExecutor(ExecutorBase):
    """``policy: shared``: episode actors hold only envs; policy actors hold the backbone."""

    policy: Literal["shared"] = Field(default="shared", description=POLICY_DOC)
    policy_actors: int = Field(default=1, ge=1, description="shared: policy actors")
    envs_per_worker: int = Field(
        default=1,
        ge=1,
        description="shared: envs each actor holds, each episode in a thread of its own, so one "
        "steps while another waits for its inference (in_actor: 1)",
    )
    policy_cpus: float = Field(default=1.0, gt=0, description="shared: CPUs per policy actor")
    max_batch: int = Field(
        default=32, ge=1, description="shared: requests (episodes) per forward at most"
    )
    batch_wait_ms: float = Field(
        default=2.0,
        ge=0,
        description="shared: how long a policy actor gathers requests for one forward",
    )
    policy_transport: Transport = Field(
        default="socket",
        description="shared: how an episode's inference reaches its policy actor: socket, over a "
        "TCP connection to the actor's own port (the env servers' frames; Ray still places, "
        "restarts and locates the actor); ray, a Ray actor call per inference (1.3-1.8 ms more "
        "on a 2-core box). The same tables either way",
    )
    policy_connections: int | None = Field(
        default=None,
        ge=1,
        description="shared, socket: connections one policy actor's socket holds at once (each "
        "after the run's token); more are refused. None: twice the episodes that may talk to it "
        "at once, plus 8",
    )
    policy_idle_s: float | None = Field(
        default=None,
        gt=0,
        description="shared, socket: a connection silent this long is closed (its episode "
        "reconnects and sends again); None: episode_timeout_s, or 900 s without one",
    )
    batching: Literal["fixed", "dynamic"] = Field(
        default="fixed",
        description="shared: fixed: every forward of the policy service has the same number of "
        "rows (executor.forward_rows), padded, so a run gives the same tables every time; "
        "dynamic: as many rows as the batch gathered (no padding; runs differ in float rounding)",
    )

    @model_validator(mode="after")
    def _one_forward_shape(self) -> SharedExecutor:
        if self.batching == "dynamic" and self.forward_rows is not None:
            raise ValueError(
                f"batching=dynamic and forward_rows={self.forward_rows} disagree: a dynamic "
                "forward has as many rows as its batch; drop one of them"
            )
        return self

    @model_validator(mode="after")
    def _socket_bounds_need_the_socket(self) -> SharedExecutor:
        given = [k for k in SOCKET_ONLY if getattr(self, k) is not None]
        if given and self.policy_transport != "socket":  # Ray calls hold no connections
            raise ValueError(_not_here(given, "policy_transport=socket"))
        return self

    def forward_shape(self) -> int | Literal["dynamic"]:
        """Rows of every forward of the policy actors: ``forward_rows``, 3 x ``max_batch``
        (an IDR request is 3 rows), or "dynamic"."""
        if self.batching == "dynamic":
            return "dynamic"
        return self.forward_rows or 3 * self.max_batch

    def threads(self) -> int:
        """torch threads of a policy actor (the only processes holding a backbone)."""
        return self.torch_threads or max(1, int(self.policy_cpus))

    def episodes_per_actor(self) -> int:
        """Episodes one episode actor runs at once: one per env it holds."""
        return self.envs_per_worker

    def episodes_per_policy_actor(self) -> int:
        """Episodes that may talk to one policy actor at once: its share of the episode actors
        (each is assigned one), each with ``envs_per_worker`` episodes."""
        actors = -(-self.workers // self.policy_actors)
        in_flight = actors * self.envs_per_worker
        return min(in_flight, self.max_in_flight) if self.max_in_flight else in_flight

    def actor_demand(self) -> dict[str, float]:
        """An episode actor holds only envs: no GPU."""
        return {**super().actor_demand(), "GPU": 0.0}

    def actor_groups(self) -> list[tuple[str, int, dict[str, float]]]:
        """The policy actors (placed first: they need the GPUs), then the episode actors."""
        policy = {"CPU": self.policy_cpus, "GPU": self.gpu_share}
        return [("executor.policy_actors", self.policy_actors, policy), *super().actor_groups()]


#: keys of the shared policy service: an in_actor run has none of them
SHARED_ONLY: tuple[str, ...] = tuple(
    k for k in SharedExecutor.model_fields if k not in ExecutorBase.model_fields
)
#: keys of the policy socket: a shared run on Ray calls has none of them
SOCKET_ONLY: tuple[str, ...] = ("policy_connections", "policy_idle_s")


def _not_here(keys: list[str], only: str) -> str:
    """The refusal of ``keys`` in a section without them: they apply to ``only`` (KEY=VALUE)."""
    one = len(keys) == 1
    return (
        f"{', '.join(f'executor.{k}' for k in keys)} {'applies' if one else 'apply'} to {only} "
        f"only: set executor.{only} or drop {'it' if one else 'them'}"
    )


class InActorExecutor(ExecutorBase):
    """``policy: in_actor`` (the default): each actor holds a backbone and an env."""

    policy: Literal["in_actor"] = Field(default="in_actor", description=POLICY_DOC)

    @model_validator(mode="before")
    @classmethod
    def _no_shared_keys(cls, data: Any) -> Any:
        """One message for the shared policy's keys, instead of "unknown key" for each: they
        are known, just not to this placement."""
        given = [k for k in SHARED_ONLY if isinstance(data, dict) and k in data]
        if given:
            raise ValueError(_not_here(given, "policy=shared"))
        return data


def _placement_or_default(data: Any) -> Any:
    """``policy`` absent: in_actor (the default), so the union knows its variant."""
    if isinstance(data, dict) and "policy" not in data:
        return {**data, "policy": "in_actor"}
    return data


#: the ``executor`` section: its variant is its ``policy`` (in_actor where absent)
ExecutorConfig = Annotated[
    InActorExecutor | SharedExecutor,
    Field(discriminator="policy"),
    BeforeValidator(_placement_or_default),
]


def without_ignored_keys(executor: dict[str, Any]) -> dict[str, Any]:
    """A run's recorded ``executor`` section without the shared-only keys of an in_actor run:
    a record (``RUN_DIR/config.yaml``) may list every key with its default, and those had no
    effect on the run. Only for reading what a run ran; a config given to run is checked
    whole."""
    if executor.get("policy", "in_actor") != "in_actor":
        return executor
    return {k: v for k, v in executor.items() if k not in SHARED_ONLY}
