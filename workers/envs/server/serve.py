"""The env server: one env in a child process, possibly of another Python, driven over a socket.

Started by :class:`workers.envs.server.client.ServerProcess` as ``python -m workers.envs.server.serve --fd N
--parent PID`` with the project root on PYTHONPATH; it needs only numpy, msgpack and what the
env itself imports (CALVIN: PyBullet on Python 3.11). It serves one request at a time over the
inherited socket (``workers.envs.server.wire``) until ``close`` or until the socket closes.

It never outlives its actor: it checks that its parent is alive every half second (an orphan
is re-parented) and exits when the socket reaches EOF; started from a main thread it also asks
the kernel for SIGKILL when the parent dies (PR_SET_PDEATHSIG). The actor kills its process
group on timeout or close.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable
from typing import Any

from workers.envs.base import episode_status
from workers.envs.server import wire

PR_SET_PDEATHSIG = 1
PARENT_POLL_S = 0.5
# a request (an op, its env params, an action) is small: a longer frame is not one (the wire's
# frame rules; the replies, images among them, are bounded by the client's reader)
REQUEST_MAX_FRAME = 64 << 20


def env_info(env: Any) -> dict[str, Any]:
    """What the actor's EnvServerClient mirrors: the Env protocol's constants and the tasks."""
    from dataclasses import asdict

    from workers.envs.base import suite_info

    info = suite_info(env)
    return {
        "suite": env.suite,
        "control_hz": float(env.control_hz),
        "action_dim": int(env.action_dim),
        "state_dim": int(env.state_dim),
        "cameras": list(env.cameras),
        "gripper_index": info.gripper_index,
        "render_backend": info.render_backend,
        "policy_reset_per_subtask": bool(info.policy_reset_per_subtask),
        "perturbation_kinds": list(info.perturbation_kinds),
        "renders_hidden_objects": bool(info.renders_hidden_objects),
        "tasks": [asdict(t) for t in env.tasks()],
    }


class EnvServer:
    """Holds one env and the last observation; ``op_<name>`` answers request ``name``."""

    def __init__(self) -> None:
        self.env: Any = None
        self.obs: Any = None

    # -- requests ----------------------------------------------------------------------------
    def op_hello(self, _: dict[str, Any]) -> dict[str, Any]:
        return {
            "version": wire.PROTOCOL_VERSION,
            "python": sys.version.split()[0],
            "executable": sys.executable,
            "pid": os.getpid(),
        }

    def op_probe(self, req: dict[str, Any]) -> dict[str, Any]:
        """Import the env class and run its runtime check (the pre-flight), build nothing."""
        from workers.envs.base import suite_hooks

        cls = self._load(req["entry"])
        check = suite_hooks(cls).check_runtime
        if check is not None:
            check(**req["params"])
        return self.op_hello(req)

    def op_init(self, req: dict[str, Any]) -> dict[str, Any]:
        if self.env is not None:
            raise RuntimeError("init: this server already holds an env")
        self.env = self._load(req["entry"])(**req["params"])
        return env_info(self.env)

    def op_reset(self, req: dict[str, Any]) -> dict[str, Any]:
        env = self._env()
        if "perturbation" in req:  # a scene perturbation (only sent where one applies)
            from workers.envs.wrappers.perturbation_grammar import parse

            env.set_perturbation(parse(req["perturbation"]))
        self.obs = env.reset(req["task_id"], int(req["episode_index"]), int(req["seed"]))
        return self._observation()

    def op_step(self, req: dict[str, Any]) -> dict[str, Any]:
        self.obs = self._env().step(req["action"])
        return self._observation()

    def op_render(self, req: dict[str, Any]) -> Any:
        if self.obs is None:
            raise RuntimeError("render: no observation yet (reset first)")
        return self.obs.images[req["camera"]]

    def op_object_hidden_images(self, _: dict[str, Any]) -> dict[str, Any]:
        """The env's object-hidden render of its current state (SuiteInfo.renders_hidden_objects)."""
        if self.obs is None:
            raise RuntimeError("object_hidden_images: no observation yet (reset first)")
        return dict(self._env().object_hidden_images())

    def op_privileged(self, _: dict[str, Any]) -> dict[str, Any]:
        if self.obs is None or self.obs.privileged is None:
            raise RuntimeError("privileged: this observation has no privileged state")
        return dict(self.obs.privileged)

    def op_close(self, _: dict[str, Any]) -> None:
        env, self.env = self.env, None
        if env is not None:
            env.close()

    # -- helpers -----------------------------------------------------------------------------
    def _env(self) -> Any:
        if self.env is None:
            raise RuntimeError("no env: send init first")
        return self.env

    @staticmethod
    def _load(entry: str) -> Any:
        from workers.registry import load_class

        return load_class({}, entry, "env.suite")

    def _observation(self) -> dict[str, Any]:
        return {
            "state": self.obs.state,
            "has_privileged": self.obs.privileged is not None,
            "status": episode_status(self.env, self.obs).to_wire(),
        }

    def handle(self, req: Any) -> dict[str, Any]:
        op = req.get("op") if isinstance(req, dict) else None
        handler: Callable[[dict[str, Any]], Any] | None = getattr(self, f"op_{op}", None)
        if not isinstance(op, str) or handler is None:
            return _error(ValueError(f"unknown request {op!r}"))
        try:
            return {"ok": True, "result": handler(req)}
        except Exception as exc:
            return _error(exc)


def _error(exc: BaseException) -> dict[str, Any]:
    return {
        "ok": False,
        "type": type(exc).__name__,
        "message": str(exc),
        "traceback": "".join(traceback.format_exception(exc)[-6:]),
    }


def serve(sock: Any, server: EnvServer | None = None) -> None:
    """Answer requests until ``close`` or until the actor's end of the socket closes."""
    server = server or EnvServer()
    while True:
        try:
            req = wire.recv(sock, REQUEST_MAX_FRAME)
        except (wire.WireError, OSError):
            return  # the actor is gone, or sent what is not a request: nobody to answer
        reply = server.handle(req)
        try:
            wire.send(sock, reply)
        except TypeError as exc:  # a result msgpack cannot carry
            wire.send(sock, _error(exc))
        if isinstance(req, dict) and req.get("op") == "close":
            return


def die_with_parent(parent_pid: int, pdeathsig: bool) -> None:
    """Exit when the actor that started us is gone, whatever it is doing."""
    if pdeathsig and sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent_pid:
        os._exit(3)

    def watch() -> None:
        while True:
            time.sleep(PARENT_POLL_S)
            if os.getppid() != parent_pid:
                os._exit(3)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def main(argv: list[str] | None = None) -> int:
    import socket

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fd", type=int, required=True, help="the inherited socket")
    parser.add_argument("--parent", type=int, required=True, help="pid of the actor")
    parser.add_argument("--pdeathsig", action="store_true", help="SIGKILL when the parent dies")
    args = parser.parse_args(argv)
    die_with_parent(args.parent, args.pdeathsig)
    sock = socket.socket(fileno=args.fd)
    try:
        serve(sock)
    finally:
        sock.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
