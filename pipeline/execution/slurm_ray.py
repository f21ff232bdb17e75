"""Ray across a Slurm allocation (``pipeline.execution.slurm``): the head on its first node, a
``ray start --block`` per other node through ``srun``, each with the CPUs and GPUs Slurm gave it
there, and the wait until every node has registered."""

from __future__ import annotations

import contextlib
import os
import shlex
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import RunError
from pipeline.execution.slurm_allocation import Allocation, node_address, srun_command

NODE_WAIT_S = 120.0  # for every Ray node of the allocation to register


@dataclass
class RayOnSlurm:
    """The Ray nodes this launcher started: the head (a child) and one ``srun`` per node."""

    address: str
    procs: list[subprocess.Popen]

    def stop(self) -> None:
        for p in reversed(self.procs):  # workers first, the head last
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    continue
        deadline = time.monotonic() + 10
        for p in self.procs:
            try:
                p.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(p.pid, signal.SIGKILL)


def _ray_bin() -> str:
    return str(Path(sys.executable).with_name("ray"))


def start_ray(alloc: Allocation, control: Path, env: dict[str, str]) -> RayOnSlurm:
    head = alloc.nodes[0]
    ip = node_address(head)
    with socket.socket() as s:  # a free port on the head for the GCS
        s.bind((ip, 0))
        port = s.getsockname()[1]
    address = f"{ip}:{port}"
    tmp = Path(os.environ.get("TMPDIR", "/tmp"))
    common = ["--block", "--disable-usage-stats"]
    procs = []
    log_dir = control / "ray-logs"
    log_dir.mkdir(exist_ok=True)

    def launch(cmd: list[str], name: str) -> None:
        with open(log_dir / f"{name}.log", "w") as f:
            procs.append(
                subprocess.Popen(
                    cmd, stdout=f, stderr=subprocess.STDOUT, env=env, start_new_session=True
                )
            )

    launch(
        [
            _ray_bin(),
            "start",
            "--head",
            f"--node-ip-address={ip}",
            f"--port={port}",
            f"--num-cpus={alloc.cpus[0]}",
            f"--num-gpus={alloc.gpus[0]}",
            f"--temp-dir={tmp / f'ray-{alloc.job_id}-{head}'}",
            "--include-dashboard=false",
            *common,
        ],
        head,
    )
    ray = RayOnSlurm(address, procs)
    try:
        # the other nodes start at once: `ray start --address` waits for the head's GCS
        for node, cpus, gpus in zip(alloc.nodes[1:], alloc.cpus[1:], alloc.gpus[1:], strict=True):
            cmd = [
                _ray_bin(),
                "start",
                f"--address={address}",
                f"--num-cpus={cpus}",
                f"--num-gpus={gpus}",
                f"--temp-dir={tmp / f'ray-{alloc.job_id}-{node}'}",
                *common,
            ]
            # in a container, `ray start` runs in it on every node (docker/slurm.sbatch)
            wrap = shlex.split(os.environ.get("IDR_EVAL_EXEC", ""))
            launch(srun_command(node, alloc, [*wrap, *cmd]), node)
        _wait_nodes(address, len(alloc.nodes), procs)
    except BaseException:
        ray.stop()
        raise
    return ray


def _wait_nodes(address: str, n: int, procs: list[subprocess.Popen]) -> None:
    from ray._raylet import GcsClient
    from ray.core.generated.gcs_pb2 import GcsNodeInfo

    deadline = time.monotonic() + NODE_WAIT_S
    alive = 0
    while time.monotonic() < deadline:
        dead = [p for p in procs if p.poll() is not None]
        if dead:
            raise RunError(
                f"a Ray node of the allocation exited (rc {dead[0].returncode}) before the run "
                "started; its log is under the run dir's .slurm-JOBID/ray-logs"
            )
        try:
            client = GcsClient(address=address)
            alive = len(
                client.get_all_node_info(
                    timeout=2, state_filter=GcsNodeInfo.GcsNodeState.ALIVE
                ).values()
            )
        except Exception:  # the GCS is still starting
            alive = 0
        if alive >= n:
            return
        time.sleep(0.5)
    raise RunError(f"{alive} of {n} Ray nodes registered at {address} in {NODE_WAIT_S:.0f} s")
