"""The serving path against the field's: one model, the same requests, several paths, one run.

Clients in processes of their own (a pool started once; B of them at a time, each sending its
requests one after another, closed loop) ask for IDR inferences (mode E: the three passes and
the refinement) of one model through:

- ``in_process``: each client holds its own copy of the model (the in-actor mode);
- ``ours``: the shared policy service, a Ray policy actor (``workers.policy.actor``) reached
  through ``PolicyServiceClient``, as an episode worker reaches it: over the actor's own socket
  (``executor.policy_transport=socket``, the default);
- ``ours_ray``: the same service with a Ray actor call per request (``policy_transport=ray``);
- ``vla_eval``: vla-eval's batching model server (``PredictModelServer`` from the vla-eval
  package, ``predict_batch`` overridden to run the same ``PolicyWorker``), on 127.0.0.1 in a
  process of its own, raw images on the wire, no action-chunk buffering (``chunk_size=None``), so
  every request is answered with a forward;
- ``openpi`` (the closed-form model only): openpi's ``WebsocketPolicyServer`` in ``.venv-openpi``
  (its numpy < 2 pin keeps lerobot out), reached through our remote backbone, which sends the
  three passes as one batched request; openpi's server does not batch across clients;
- ``ray_floor``: a bare threaded Ray actor that answers the same request payload with a stored
  answer of the same size: what one Ray call costs here.

Both batching servers wait the same ``--wait-ms`` for a batch (ours: ``executor.batch_wait_ms``;
vla-eval's ``max_wait_time``) and take at most ``--max-batch`` requests per forward. Models: the
tiny VLA (``checkpoints/tiny_vla``, two 96 px cameras, 8-d state) and the closed-form fake
(``workers.backbones.websocket.fake_backbone``: near-zero compute, one camera).

Per B concurrent clients: the round trip (median, p90), the throughput mu(B) (requests answered
per second), and the per-request overhead, round trip minus the in-process compute of one forward
of B requests (``PolicyWorker.infer_each`` in this process, nothing else running). The breakdown
of ours at B = 1 (both transports) splits the round trip into the client's work, the transport,
the handoff to and from the batching thread, and the forward. A peer that cannot be installed or reached is
recorded as skipped, with the reason.

Writes ``benchmarks/results/serving.json``.
Usage: ``python benchmarks/bench_serving.py [--requests 240] [--clients 1,4,16] [--wait-ms 2]``
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import socket
import statistics
import subprocess
import sys
import time
import traceback
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
RESULTS = Path(__file__).parent / "results" / "serving.json"
NAMESPACE = "bench_serving"
INSTRUCTION = "pick up the red cube"
OPENPI_PYTHON = ROOT / ".venv-openpi" / "bin" / "python"
MODELS: dict[str, dict[str, Any]] = {
    "tiny_vla": {
        "kind": "lerobot",
        "params": {"path": str(ROOT / "checkpoints" / "tiny_vla"), "device": "cpu"},
        "cameras": ("agentview", "wrist"),
        "state_dim": 8,
    },
    "closed_form": {
        "kind": "workers.backbones.websocket.fake_backbone:ClosedFormBackbone",
        "params": {},
        "cameras": ("agentview",),
        "state_dim": 8,
    },
}
PATHS = ("in_process", "ours", "ours_ray", "vla_eval", "openpi", "ray_floor")
SERVICE = {"ours": "socket", "ours_ray": "ray"}  # our service's paths: their transport
SIZE = 96
OBSERVATIONS = 8  # distinct observations per client, cycled


# -- what every path sends ----------------------------------------------------------------------


def raw_observations(model: str, client: int) -> list[Any]:
    """The env's observations a client sends (uint8 HWC images, float32 state)."""
    from workers.envs.base import EnvObservation

    m = MODELS[model]
    rng = np.random.default_rng([client, 7])
    return [
        EnvObservation(
            images={c: rng.integers(0, 256, (SIZE, SIZE, 3), dtype=np.uint8) for c in m["cameras"]},
            state=rng.standard_normal(m["state_dim"]).astype(np.float32),
        )
        for _ in range(OBSERVATIONS)
    ]


def wire_request(raw: Any, seed: int) -> Any:
    """The request a server builds from one raw observation (uint8 (1, 3, H, W) images, as our
    client sends them), for mode E."""
    from idr_core.interventions import InterventionConfig
    from idr_core.refiner import RefinerConfig

    from workers.backbones.base import Observation
    from workers.policy.service import InferRequest

    images = {k: np.ascontiguousarray(v.transpose(2, 0, 1))[None] for k, v in raw.images.items()}
    state = np.asarray(raw.state, dtype=np.float32)[None]
    obs = Observation(images=images, state=state, instruction=[INSTRUCTION])
    return InferRequest(obs, int(seed), RefinerConfig(mode="E"), InterventionConfig())


def answer_dict(step: Any) -> dict[str, Any]:
    """An IDR step as vla-eval's action dict: the same arrays ours returns."""
    out: dict[str, Any] = {"actions": np.asarray(step.action, dtype=np.float32)}
    for k in ("a_base", "a_no_img", "a_no_prop"):
        out[k] = np.asarray(getattr(step, k), dtype=np.float32)
    if step.diag is not None:
        out["diag"] = {k: np.asarray(v) for k, v in step.diag.to_numpy().items()}
    return out


# -- vla-eval's server (its own process) --------------------------------------------------------


def serve_vla_eval(model: str, port: int, max_batch: int, wait_ms: float, stats: Path) -> None:
    """vla-eval's batching server around our PolicyWorker (runs until killed)."""
    import signal

    from vla_eval.model_servers.predict import PredictModelServer
    from vla_eval.model_servers.serve import serve
    from vla_eval.specs import IMAGE_RGB, LANGUAGE, RAW

    from workers.envs.base import EnvObservation
    from workers.policy.service import PolicyWorker

    m = MODELS[model]

    class IDRModelServer(PredictModelServer):
        def __init__(self) -> None:
            # chunk_size None: no chunk buffer, every observation is a forward
            super().__init__(chunk_size=None, max_batch_size=max_batch, max_wait_time=wait_ms / 1e3)
            self.worker = PolicyWorker(m["kind"], m["params"], threads=1)
            self.batch_sizes: list[int] = []

        def predict_batch(self, obs_batch: list[Any], ctx_batch: list[Any]) -> list[Any]:
            self.batch_sizes.append(len(obs_batch))
            reqs = [
                wire_request(EnvObservation(images=o["images"], state=o["state"]), o["seed"])
                for o in obs_batch
            ]
            return [answer_dict(s) for s in self.worker.infer_many(reqs)]

        def get_action_spec(self) -> dict[str, Any]:
            return {"actions": RAW}

        def get_observation_spec(self) -> dict[str, Any]:
            return {"image": IMAGE_RGB, "language": LANGUAGE}

    server = IDRModelServer()

    def stop(*_: Any) -> None:
        sizes = server.batch_sizes
        stats.write_text(json.dumps({"forwards": len(sizes), "requests": sum(sizes)}))
        os._exit(0)

    signal.signal(signal.SIGTERM, stop)
    serve(server, host="127.0.0.1", port=port)


# -- the clients (a pool of processes) ----------------------------------------------------------


class _ClientState:
    def __init__(self) -> None:
        self.models: dict[str, Any] = {}
        self.ray_address: str | None = None


def _wait_until(t: float) -> None:
    while (left := t - time.time()) > 0:
        time.sleep(min(left, 0.05))


def _timed(call: Any, raws: list[Any], n: int, warmup: int, ready: Any) -> dict[str, Any]:
    for i in range(warmup):
        call(raws[i % len(raws)], 10_000 + i)
    _wait_until(ready())  # every client warm, then one start for all
    rtt = []
    t0 = time.time()
    for i in range(n):
        s = time.perf_counter()
        call(raws[i % len(raws)], i)
        rtt.append((time.perf_counter() - s) * 1e3)
    return {"rtt_ms": rtt, "t0": t0, "t1": time.time()}


def _run_job(job: dict[str, Any], state: _ClientState, ready: Any) -> dict[str, Any]:
    """One path's timed requests; ``ready()`` says this client is warm and returns the
    wall-clock time every client starts at."""
    from idr_core.refiner import RefinerConfig

    from workers.episode.observation import to_policy_observation

    path, model, ep = job["path"], job["model"], job["endpoint"]
    m = MODELS[model]
    raws = raw_observations(model, job["client"])
    n, warmup = job["n"], job["warmup"]

    def policy_obs(raw: Any) -> Any:
        return to_policy_observation(raw, INSTRUCTION, m["cameras"])

    if path in (*SERVICE, "ray_floor") and state.ray_address != ep["ray_address"]:
        import ray

        ray.init(address=ep["ray_address"], namespace=NAMESPACE, log_to_driver=False)
        state.ray_address = ep["ray_address"]
    if path == "in_process":
        from workers.backbones.factory import make_backbone
        from workers.policy.wrapper import IDRWrapper

        if model not in state.models:
            state.models[model] = IDRWrapper(make_backbone(m["kind"], m["params"]))
        policy = state.models[model]
        cfg = RefinerConfig(mode="E")
        return _timed(
            lambda raw, seed: policy.infer(policy_obs(raw), seed, cfg), raws, n, warmup, ready
        )
    if path in SERVICE:
        import ray

        from workers.policy.actor import connect

        client = connect(ray.get_actor(ep["actor"]), RefinerConfig(mode="E"))
        return _timed(lambda raw, seed: client.infer(policy_obs(raw), seed), raws, n, warmup, ready)
    if path == "ray_floor":
        import ray

        echo = ray.get_actor(ep["actor"])
        request = wire_request(raws[0], 0)
        return _timed(lambda raw, seed: ray.get(echo.infer.remote(request)), raws, n, warmup, ready)
    if path == "openpi":
        from workers.backbones.websocket.client import WebsocketBackbone
        from workers.backbones.websocket.fake_backbone import KEY_MAP
        from workers.policy.wrapper import IDRWrapper

        backbone = WebsocketBackbone(port=ep["port"], key_map=KEY_MAP)
        try:
            policy = IDRWrapper(backbone, RefinerConfig(mode="E"))
            return _timed(
                lambda raw, seed: policy.infer(policy_obs(raw), seed), raws, n, warmup, ready
            )
        finally:
            backbone.close()
    if path == "vla_eval":
        return _vla_eval_client(ep["url"], raws, n, warmup, ready)
    raise ValueError(f"unknown path {path!r}")


def _vla_eval_client(url: str, raws: list[Any], n: int, warmup: int, ready: Any) -> dict[str, Any]:
    import anyio
    from vla_eval.connection import Connection
    from vla_eval.protocol.numpy_codec import set_image_format

    set_image_format("raw")  # as ours: uint8 pixels, no PNG

    async def run() -> dict[str, Any]:
        async with Connection(url, timeout=60.0) as conn:
            await conn.start_episode({"task": {"name": "bench"}})

            async def call(raw: Any, seed: int) -> None:
                obs = {
                    "images": dict(raw.images),
                    "state": raw.state,
                    "task_description": INSTRUCTION,
                    "seed": seed,
                }
                await conn.act(obs)

            for i in range(warmup):
                await call(raws[i % len(raws)], 10_000 + i)
            start_at = ready()  # blocks the loop: nothing else runs on it
            while (left := start_at - time.time()) > 0:
                await anyio.sleep(min(left, 0.05))
            rtt = []
            t0 = time.time()
            for i in range(n):
                s = time.perf_counter()
                await call(raws[i % len(raws)], i)
                rtt.append((time.perf_counter() - s) * 1e3)
            t1 = time.time()
            await conn.end_episode({"success": False})
            return {"rtt_ms": rtt, "t0": t0, "t1": t1}

    return anyio.run(run)


def _client_main(conn: Any) -> None:
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    import torch

    torch.set_num_threads(1)
    state = _ClientState()

    def ready() -> float:
        conn.send(("ready", None))
        return conn.recv()

    while (job := conn.recv()) is not None:
        try:
            conn.send(("ok", _run_job(job, state, ready)))
        except Exception:
            conn.send(("error", traceback.format_exc()))


class ClientPool:
    """Client processes started once (spawned: no state inherited from this one)."""

    def __init__(self, size: int) -> None:
        ctx = mp.get_context("spawn")
        self.conns = []
        self.procs = []
        for _ in range(size):
            parent, child = ctx.Pipe()
            p = ctx.Process(target=_client_main, args=(child,), daemon=True)
            p.start()
            self.conns.append(parent)
            self.procs.append(p)

    def run(self, jobs: list[dict[str, Any]]) -> list[dict[str, Any]]:
        """Each job on a client of its own; the timed requests start together once every
        client has connected, loaded and warmed up."""
        conns = self.conns[: len(jobs)]
        for conn, job in zip(conns, jobs, strict=True):
            conn.send(job)
        for conn in conns:
            status, value = conn.recv()
            if status == "error":
                raise RuntimeError(f"client failed:\n{value}")
        start_at = time.time() + 0.2
        for conn in conns:
            conn.send(start_at)
        out = []
        for conn in conns:
            status, value = conn.recv()
            if status != "ok":
                raise RuntimeError(f"client failed:\n{value}")
            out.append(value)
        return out

    def close(self) -> None:
        for conn in self.conns:
            conn.send(None)
        for p in self.procs:
            p.join(timeout=30)


# -- servers ------------------------------------------------------------------------------------


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_port(port: int, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"the server exited with {proc.returncode} before listening")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1):
                return
        except OSError:
            time.sleep(0.2)
    raise RuntimeError(f"no server on port {port} after {timeout:.0f} s")


class Server:
    """One path's server for one model: its endpoint for the clients, stopped by ``close``."""

    def __init__(self, path: str, model: str, args: argparse.Namespace, ray_address: str) -> None:
        self.path, self.model = path, model
        self.proc: subprocess.Popen | None = None
        self.actor: Any = None
        self.stats_file = Path(f"/tmp/bench_serving_{os.getpid()}_{path}_{model}.json")
        m = MODELS[model]
        if path == "in_process":
            self.endpoint: dict[str, Any] = {}
        elif path in SERVICE:
            import ray

            from workers.policy.actor import policy_actor_class

            name = f"policy_{path}_{model}"
            cls = policy_actor_class(1, 0).options(name=name, namespace=NAMESPACE)
            self.actor = cls.remote(
                m["kind"], m["params"], None, args.max_batch, args.wait_ms, None, None, 1,
                transport=SERVICE[path],
            )  # fmt: skip
            ray.get(self.actor.describe.remote())  # loaded
            self.endpoint = {"ray_address": ray_address, "actor": name}
        elif path == "ray_floor":
            import ray

            answer = Echo.answer_to(m, wire_request(raw_observations(model, 0)[0], 0))
            cls = ray.remote(num_cpus=1, max_concurrency=256)(Echo)
            self.actor = cls.options(name=f"echo_{model}", namespace=NAMESPACE).remote(answer)
            ray.get(self.actor.ping.remote())
            self.endpoint = {"ray_address": ray_address, "actor": f"echo_{model}"}
        elif path == "vla_eval":
            import vla_eval  # noqa: F401  (skipped with the reason if it is not installed)

            port = _port()
            self.proc = subprocess.Popen(
                [
                    sys.executable,
                    __file__,
                    "--serve-vla-eval",
                    model,
                    "--port",
                    str(port),
                    "--max-batch",
                    str(args.max_batch),
                    "--wait-ms",
                    str(args.wait_ms),
                    "--stats",
                    str(self.stats_file),
                ],
                cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"},
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            _wait_port(port, self.proc)
            self.endpoint = {"url": f"ws://127.0.0.1:{port}"}
        elif path == "openpi":
            if model != "closed_form":
                raise Skip("openpi's server runs in .venv-openpi (numpy < 2): no lerobot there")
            if not OPENPI_PYTHON.exists():
                raise Skip(f"{OPENPI_PYTHON} missing (scripts/setup_openpi.sh, run by make setup)")
            port = _port()
            self.proc = subprocess.Popen(
                [
                    str(OPENPI_PYTHON),
                    "-m",
                    "workers.backbones.websocket.fake_server_openpi",
                    *("--port", str(port), "--batch", "--noise-std", "0"),
                ],
                cwd=ROOT,
                env={**os.environ, "PYTHONPATH": str(ROOT)},
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            _wait_port(port, self.proc)
            self.endpoint = {"port": port}
        else:
            raise ValueError(path)

    def stats(self) -> dict[str, Any]:
        import ray

        if self.path in SERVICE:
            return ray.get(self.actor.stats.remote())
        return {}

    def close(self) -> dict[str, Any]:
        """Stop the server; its forward count where it keeps one."""
        out: dict[str, Any] = {}
        if self.actor is not None:
            import ray

            ray.kill(self.actor)
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(timeout=30)
            if self.stats_file.exists():
                out = json.loads(self.stats_file.read_text())
                self.stats_file.unlink()
        return out


class Echo:
    """The floor: a threaded Ray actor (as the policy actor) answering with a stored step; with
    ``busy_ms``, after holding its thread (and the GIL) that long, as a forward would."""

    def __init__(self, answer: Any, busy_ms: float = 0.0) -> None:
        self.answer = answer
        self.busy_s = busy_ms / 1e3

    @staticmethod
    def answer_to(model: dict[str, Any], request: Any) -> Any:
        """The step ``model`` (a ``MODELS`` entry) answers ``request`` with, as it crosses back."""
        from workers.policy.service import PolicyWorker, to_numpy_step

        worker = PolicyWorker(model["kind"], model["params"], threads=1)
        return to_numpy_step(worker.infer_many([request])[0])

    def ping(self) -> None:
        pass

    def infer(self, request: Any, client: str | None = None) -> Any:
        if self.busy_s:
            end = time.perf_counter() + self.busy_s
            while time.perf_counter() < end:
                pass
        return self.answer


class Skip(Exception):
    """A path that cannot run here; recorded with the reason."""


# -- measurement --------------------------------------------------------------------------------


def compute_ms(model: str, batches: list[int], rounds: int) -> dict[int, float]:
    """In-process compute of one forward of B requests (the median over rounds)."""
    import torch

    from workers.policy.service import PolicyWorker

    torch.set_num_threads(1)
    m = MODELS[model]
    worker = PolicyWorker(m["kind"], m["params"], threads=1)
    raws = raw_observations(model, 0)
    out = {}
    for b in batches:
        reqs = [wire_request(raws[i % len(raws)], i) for i in range(b)]
        worker.infer_many(reqs)
        times = []
        for _ in range(rounds):
            t0 = time.perf_counter()
            worker.infer_many(reqs)
            times.append((time.perf_counter() - t0) * 1e3)
        out[b] = statistics.median(times)
    return out


def measure(
    pool: ClientPool, server: Server, b: int, args: argparse.Namespace, compute: float
) -> dict[str, Any]:
    n = max(math.ceil(args.requests / b), 20)
    jobs = [
        {
            "path": server.path,
            "model": server.model,
            "endpoint": server.endpoint,
            "client": c,
            "n": n,
            "warmup": 5,
        }
        for c in range(b)
    ]
    before = server.stats()
    results = pool.run(jobs)
    after = server.stats()
    rtt = sorted(x for r in results for x in r["rtt_ms"])
    wall = max(r["t1"] for r in results) - min(r["t0"] for r in results)
    median = statistics.median(rtt)
    row: dict[str, Any] = {
        "clients": b,
        "requests": len(rtt),
        "rtt_ms_median": median,
        "rtt_ms_p90": rtt[int(0.9 * (len(rtt) - 1))],
        "mu_per_s": len(rtt) / wall,
        "compute_ms": compute,
        "overhead_ms": median - compute,
    }
    if before and after:
        forwards = after["forwards"] - before["forwards"]
        row["mean_batch"] = (after["requests"] - before["requests"]) / max(forwards, 1)
    return row


def breakdown(
    model: str, args: argparse.Namespace, transport: str, calls: int = 300
) -> dict[str, Any]:
    """Where ours' round trip goes at B = 1, in this process (a client of its own): the client's
    work (to_policy_observation and the request built from it), the policy actor's time from
    receiving the request to answering it (the forward, and the handoff to and from the batching
    thread), the forward itself, and the rest: the transport (``socket``: encoding, the
    connection and decoding; ``ray``: Ray's serialization, transport and scheduling)."""
    import ray
    from idr_core.refiner import RefinerConfig

    from workers.episode.observation import to_policy_observation
    from workers.policy.actor import connect, policy_actor_class

    m = MODELS[model]
    raws = raw_observations(model, 0)
    actor = policy_actor_class(1, 0).remote(
        m["kind"], m["params"], None, args.max_batch, args.wait_ms, None, None, 1,
        transport=transport,
    )  # fmt: skip
    client = connect(actor, RefinerConfig(mode="E"))
    obs = [to_policy_observation(r, INSTRUCTION, m["cameras"]) for r in raws]
    for i in range(10):
        client.infer(obs[i % len(obs)], i)
    s0 = ray.get(actor.stats.remote())
    rtt = []
    for i in range(calls):
        t0 = time.perf_counter()
        client.infer(to_policy_observation(raws[i % len(raws)], INSTRUCTION, m["cameras"]), i)
        rtt.append(time.perf_counter() - t0)
    s1 = ray.get(actor.stats.remote())
    client.close()
    ray.kill(actor)
    forward = (s1["busy_s"] - s0["busy_s"]) / max(s1["forwards"] - s0["forwards"], 1) * 1e3

    # the floor with the same compute: a bare Ray call to an actor that holds its thread for the
    # forward's time, so what is left of ours beyond it is ours, not what Ray costs around a
    # busy actor on shared cores
    wired = client.request(obs[0], 0)
    busy = ray.remote(num_cpus=0, max_concurrency=256)(Echo).remote(
        Echo.answer_to(m, wired), forward
    )
    for _ in range(10):
        ray.get(busy.infer.remote(wired, client.client_id))
    busy_rtt = []
    for i in range(calls):
        t0 = time.perf_counter()
        ray.get(busy.infer.remote(client.request(obs[i % len(obs)], i), client.client_id))
        busy_rtt.append(time.perf_counter() - t0)
    ray.kill(busy)

    def per_call(f: Any) -> float:
        times = []
        for i in range(calls):
            t0 = time.perf_counter()
            f(i)
            times.append(time.perf_counter() - t0)
        return statistics.median(times) * 1e3

    request = wire_request(raws[0], 0)
    build = getattr(client, "request", None)  # absent before the client built requests apart
    prep = (
        None
        if build is None
        else per_call(
            lambda i: build(
                to_policy_observation(raws[i % len(raws)], INSTRUCTION, m["cameras"]), i
            )
        )
    )
    served = s1["served_ms_median"]
    total = statistics.median(rtt) * 1e3
    return {
        "round_trip_ms": total,
        "client_ms": prep,
        "actor_forward_ms": forward,
        "actor_handoff_ms": served - forward,
        "transport": transport,
        "transport_ms": total - (prep or 0.0) - served,
        "request_image_bytes": sum(v.nbytes for v in request.obs.images.values()),
        "ray_floor_busy_ms": statistics.median(busy_rtt) * 1e3,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=240, help="timed requests per (path, B)")
    ap.add_argument("--clients", default="1,4,16", help="B: concurrent clients")
    ap.add_argument("--wait-ms", type=float, default=2.0, help="both servers' batching wait")
    ap.add_argument("--max-batch", type=int, default=16)
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--paths", default=",".join(PATHS))
    ap.add_argument("--rounds", type=int, default=20, help="rounds of the in-process compute")
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument(
        "--repeat-of",
        type=Path,
        default=None,
        help="a results file to add this run's rows to as a repeat (its 'repeats' list), "
        "instead of writing --out: the spread between runs on one machine",
    )
    ap.add_argument("--serve-vla-eval", metavar="MODEL", help=argparse.SUPPRESS)
    ap.add_argument("--port", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--stats", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    os.environ.setdefault("HF_HUB_OFFLINE", "1")
    if args.serve_vla_eval:
        serve_vla_eval(args.serve_vla_eval, args.port, args.max_batch, args.wait_ms, args.stats)
        return
    import ray

    from workers.hardware import machine_record

    clients = [int(x) for x in args.clients.split(",")]
    models = args.models.split(",")
    paths = args.paths.split(",")
    ctx = ray.init(num_cpus=2, namespace=NAMESPACE, include_dashboard=False, log_to_driver=False)
    ray_address = ctx.address_info["gcs_address"]
    pool = ClientPool(max(clients))
    result: dict[str, Any] = {
        "what": "IDR inference (mode E) of one model served to B concurrent client processes "
        "through each path; overhead = round-trip median - in-process compute of one forward of "
        "B requests",
        "wait_ms": args.wait_ms,
        "max_batch": args.max_batch,
        "requests_per_row": args.requests,
        "models": {},
    }
    try:
        for model in models:
            compute = compute_ms(model, clients, args.rounds)
            print(
                f"{model}: in-process compute per forward "
                + ", ".join(f"B={b} {compute[b]:.2f} ms" for b in clients),
                flush=True,
            )
            entry: dict[str, Any] = {"compute_ms": {str(b): compute[b] for b in clients}}
            for path in paths:
                try:
                    server = Server(path, model, args, ray_address)
                except Skip as e:
                    entry[path] = {"skipped": str(e)}
                    print(f"{model} {path}: skipped ({e})", flush=True)
                    continue
                except Exception as e:  # a peer that cannot be installed or reached
                    entry[path] = {"skipped": f"{type(e).__name__}: {e}"}
                    print(f"{model} {path}: skipped ({type(e).__name__}: {e})", flush=True)
                    continue
                rows = []
                try:
                    for b in clients:
                        compute_b = 0.0 if path == "ray_floor" else compute[b]
                        row = measure(pool, server, b, args, compute_b)
                        rows.append(row)
                        print(
                            f"{model:<12} {path:<10} B={b:>2}: rtt {row['rtt_ms_median']:7.2f} ms "
                            f"(p90 {row['rtt_ms_p90']:7.2f}), mu {row['mu_per_s']:7.1f}/s, "
                            f"overhead {row['overhead_ms']:6.2f} ms"
                            + (
                                f", mean batch {row['mean_batch']:.1f}"
                                if "mean_batch" in row
                                else ""
                            ),
                            flush=True,
                        )
                finally:
                    server_stats = server.close()
                entry[path] = {"rows": rows, **({"server": server_stats} if server_stats else {})}
            entry["ratios"] = ratios(entry, clients)
            entry["breakdown_b1"] = {}
            for path, transport in SERVICE.items():
                if path in paths:
                    entry["breakdown_b1"][transport] = breakdown(model, args, transport)
                    print(f"{model} {path} at B=1: {entry['breakdown_b1'][transport]}", flush=True)
            result["models"][model] = entry
    finally:
        pool.close()
        ray.shutdown()
    result["machine"] = machine_record()
    if args.repeat_of is not None:
        base = json.loads(args.repeat_of.read_text())
        if base["machine"]["cpu_model"] != result["machine"]["cpu_model"]:
            raise SystemExit(f"{args.repeat_of} was measured on another CPU: not a repeat")
        base.setdefault("repeats", []).append(result)
        args.repeat_of.write_text(json.dumps(base, indent=2) + "\n")
        print(f"added a repeat to {args.repeat_of}")
        return
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {args.out}")


def ratios(entry: dict[str, Any], clients: list[int]) -> dict[str, Any]:
    """Ours against each other path, per B: overhead ratio and mu ratio."""

    def row(path: str, b: int) -> dict[str, Any] | None:
        rows = entry.get(path, {}).get("rows", [])
        return next((r for r in rows if r["clients"] == b), None)

    out: dict[str, Any] = {}
    for other in ("ours_ray", "vla_eval", "openpi", "ray_floor"):
        per_b = {}
        for b in clients:
            ours, theirs = row("ours", b), row(other, b)
            if ours is None or theirs is None:
                continue
            per_b[str(b)] = {
                "overhead_ratio": ours["overhead_ms"] / theirs["overhead_ms"]
                if theirs["overhead_ms"] > 0
                else None,
                "mu_ratio": ours["mu_per_s"] / theirs["mu_per_s"],
            }
        if per_b:
            out[f"ours_vs_{other}"] = per_b
    return out


if __name__ == "__main__":
    main()
