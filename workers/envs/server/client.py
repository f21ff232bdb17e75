"""An env whose simulator runs in an env server: a child process, possibly of another Python.

:class:`EnvServerClient` is the actor's side. It is an ``Env`` like any other (``check_env``, lazy
rendering per camera, failure causes, the optional members), so the episode loop does not
know where the simulator lives. Images and the privileged state are fetched on first read,
like an in-process env renders them; the status after each reset and step comes with the
reply, as the record ``EnvObservation.status``.

Lifecycle: one server per actor, started with the env (``start_timeout_s`` for the handshake
and the build), health-checked before each reset (a dead one is restarted), killed with its
process group when a request takes longer than ``timeout_s`` or at close. A server that dies
or hangs raises :class:`EnvServerError`: an actor-level fault, after which the actor restarts
it and runs the episode again (``workers.episode.worker``); an exception the env itself raises keeps
its type (ValueError, RuntimeError...) and is the episode's, as in-process.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import subprocess
import tempfile
import threading
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from workers.envs.base import EnvObservation, EpisodeStatus, LazyImages, LazyState, TaskSpec
from workers.envs.server import wire
from workers.envs.server.spec import ServerSpec

log = logging.getLogger(__name__)

PROJECT_ROOT = str(Path(__file__).resolve().parents[3])  # holds workers/: the server's import path
LOG_TAIL_BYTES = 4000
# exception types an env raises on purpose (check_env relies on ValueError / RuntimeError)
_KEPT_TYPES: dict[str, type[Exception]] = {
    t.__name__: t for t in (ValueError, RuntimeError, KeyError, TypeError, NotImplementedError)
}


class EnvServerError(RuntimeError):
    """The env server died, hung or could not start: a fault of the actor's machinery, not of
    the episode (the actor restarts the server and runs the episode again)."""


class EnvServerDied(EnvServerError):
    pass


class EnvServerTimeout(EnvServerError):
    pass


class EnvServerStartError(EnvServerError):
    """The server did not come up: a wrong interpreter, a missing package, another protocol."""


class RemoteEnvError(RuntimeError):
    """An exception the env raised inside the server, of a type not kept (its name is said)."""


class ServerProcess:
    """A started env server process: its socket, its output (kept in a temporary file whose
    tail goes into error messages) and its process group."""

    def __init__(self, python: str, timeout_s: float) -> None:
        self.python, self.timeout_s = python, timeout_s
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        self._log = tempfile.TemporaryFile(prefix="idr-env-server-")  # noqa: SIM115 (closed in close())
        cmd = [python, "-m", "workers.envs.server.serve"]
        cmd += ["--fd", str(theirs.fileno()), "--parent", str(os.getpid())]
        if threading.current_thread() is threading.main_thread():
            # PR_SET_PDEATHSIG fires when the creating *thread* exits: only from the main one
            cmd.append("--pdeathsig")
        try:
            self.proc = subprocess.Popen(
                cmd,
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,
                stdout=self._log,
                stderr=subprocess.STDOUT,
                env=_server_environ(),
                cwd=PROJECT_ROOT,
                start_new_session=True,  # its own process group: killed as one
            )
        except OSError as e:
            ours.close()
            self._log.close()
            raise EnvServerStartError(f"cannot start the env server with {python}: {e}") from None
        finally:
            theirs.close()
        self.sock = ours
        self.pid = self.proc.pid

    @property
    def alive(self) -> bool:
        return self.proc.poll() is None

    def output_tail(self) -> str:
        try:
            self._log.flush()
            size = self._log.seek(0, os.SEEK_END)
            self._log.seek(max(0, size - LOG_TAIL_BYTES))
            return self._log.read().decode(errors="replace").strip()
        except (OSError, ValueError):
            return ""

    def call(self, op: str, timeout_s: float | None = None, **args: Any) -> Any:
        timeout = timeout_s or self.timeout_s
        if not self.alive:
            raise self._died(op)
        self.sock.settimeout(timeout)
        try:
            wire.send(self.sock, {"op": op, **args})
            reply = wire.recv(self.sock)
        except TimeoutError:
            self.kill()
            raise EnvServerTimeout(
                f"the env server (pid {self.pid}) did not answer {op!r} within {timeout:g} s "
                "(env.server_timeout_s); it was killed"
            ) from None
        except (wire.WireError, OSError):
            raise self._died(op) from None
        except BaseException:  # interrupted mid-request (an episode timeout, ^C): the reply
            self.kill()  # would arrive out of turn, so this server is done; reset starts anew
            raise
        if not isinstance(reply, dict) or "ok" not in reply:
            self.kill()
            raise EnvServerError(f"the env server answered {op!r} with {reply!r}: not a reply")
        if not reply["ok"]:
            raise _remote_exception(op, reply)
        return reply["result"]

    def _died(self, op: str) -> EnvServerDied:
        try:
            code = self.proc.wait(timeout=2)
        except subprocess.TimeoutExpired:
            code = None
        self.kill()
        how = f"signal {-code}" if code is not None and code < 0 else f"exit code {code}"
        tail = self.output_tail()
        return EnvServerDied(
            f"the env server (pid {self.pid}, {self.python}) died during {op!r} ({how})"
            + (f"; its last output:\n{tail}" if tail else "")
        )

    def kill(self) -> None:
        """SIGKILL to the server's process group (anything it started dies with it). Idempotent."""
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(self.pid, signal.SIGKILL)
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            log.warning("env server %d did not die after SIGKILL", self.pid)
        self.sock.close()

    def close(self) -> None:
        """Ask the env to close (it may free a GPU context or files), then kill the group."""
        if self.alive:
            try:
                self.call("close", timeout_s=min(10.0, self.timeout_s))
            except Exception as e:  # closing anyway
                log.debug("env server %d close: %s", self.pid, e)
        self.kill()
        self._log.close()


def _server_environ() -> dict[str, str]:
    """The actor's environment minus what would make another Python import this one's
    packages (a venv, PYTHONPATH, user site), plus the project root on the import path."""
    env = {
        k: v
        for k, v in os.environ.items()
        if k not in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "PYTHONSTARTUP")
    }
    env["PYTHONPATH"] = PROJECT_ROOT
    env["PYTHONNOUSERSITE"] = "1"
    env.pop("__PYVENV_LAUNCHER__", None)
    return env


def _remote_exception(op: str, reply: Mapping[str, Any]) -> Exception:
    name, message = str(reply.get("type")), str(reply.get("message"))
    where = f"\n(raised in the env server during {op!r}:\n{reply.get('traceback', '').rstrip()})"
    kept = _KEPT_TYPES.get(name)
    if kept is KeyError:
        return KeyError(message)
    if kept is not None:
        return kept(message + where)
    return RemoteEnvError(f"{name}: {message}{where}")


def start_server(spec: ServerSpec) -> tuple[ServerProcess, dict[str, Any]]:
    """A server that answered the handshake in our protocol version, and its hello."""
    server = ServerProcess(spec.python, spec.timeout_s)
    try:
        hello = server.call("hello")
    except EnvServerError as e:
        server.kill()
        raise EnvServerStartError(
            f"the env server did not start with env.python={spec.python}: {e}. It needs numpy "
            "and msgpack in that interpreter"
        ) from None
    if hello.get("version") != wire.PROTOCOL_VERSION:
        server.close()
        raise EnvServerStartError(
            f"the env server started with env.python={spec.python} speaks protocol version "
            f"{hello.get('version')}, this actor {wire.PROTOCOL_VERSION}: the interpreter sees "
            f"another copy of this project (its PYTHONPATH must lead to {PROJECT_ROOT})"
        )
    return server, hello


def probe_server(spec: ServerSpec, entry: str, params: dict[str, Any]) -> dict[str, Any]:
    """Start a server, import the env class there and run its ``check_runtime`` (the driver's
    pre-flight: nothing is built); its hello. Raises EnvServerStartError or the env's error."""
    server, _ = start_server(spec)
    try:
        return dict(server.call("probe", entry=entry, params=params))
    finally:
        server.close()


class EnvServerClient:
    """The Env protocol over an env server (see the module docstring)."""

    def __init__(self, entry: str, params: dict[str, Any], server: ServerSpec) -> None:
        self.entry, self.params, self.server_spec = entry, dict(params), server
        self.restarts = 0
        self._server: ServerProcess | None = None
        self._generation = 0
        self._perturbation: Any = None
        self._start()

    def _start(self) -> None:
        self._server, self.hello = start_server(self.server_spec)
        try:
            info = self._server.call("init", entry=self.entry, params=self.params)
        except BaseException:
            self._server.close()
            raise
        self.suite: str = info["suite"]
        self.control_hz: float = info["control_hz"]
        self.action_dim: int = info["action_dim"]
        self.state_dim: int = info["state_dim"]
        self.cameras: tuple[str, ...] = tuple(info["cameras"])
        self.gripper_index: int | None = info["gripper_index"]
        self.render_backend: str | None = info["render_backend"]
        self.policy_reset_per_subtask: bool = info["policy_reset_per_subtask"]
        self.perturbation_kinds: tuple[str, ...] = tuple(info.get("perturbation_kinds", ()))
        self.renders_hidden_objects: bool = bool(info.get("renders_hidden_objects", False))
        self._tasks = [TaskSpec(**t) for t in info["tasks"]]
        self._generation += 1  # observations of the old server are stale

    @property
    def pid(self) -> int | None:
        return self._server.pid if self._server is not None else None

    @property
    def alive(self) -> bool:
        return self._server is not None and self._server.alive

    def restart(self) -> None:
        """Kill the server (if any) and start a fresh one with the same env."""
        if self._server is not None:
            self._server.close()
        self.restarts += 1
        self._start()

    def _call(self, op: str, **args: Any) -> Any:
        if self._server is None:
            raise RuntimeError("the env is closed")
        return self._server.call(op, **args)

    # -- Env protocol ------------------------------------------------------------------------
    def tasks(self) -> list[TaskSpec]:
        return list(self._tasks)

    def reset(self, task_id: str, episode_index: int, seed: int) -> EnvObservation:
        if not self.alive:  # health check: a server that died between episodes is replaced
            log.warning("env server %s is gone; starting a new one", self.pid)
            self.restart()
        args: dict[str, Any] = {"task_id": task_id, "episode_index": episode_index, "seed": seed}
        if self._perturbation is not None or self.perturbation_kinds:
            args["perturbation"] = self._perturbation.text if self._perturbation else "none"
        return self._observation(self._call("reset", **args))

    def set_perturbation(self, p: Any) -> None:
        """The scene perturbation of the next reset, applied by the env in the server."""
        if p is not None and p.kind not in self.perturbation_kinds:
            raise ValueError(f"the env cannot apply {p.kind}; it applies {self.perturbation_kinds}")
        self._perturbation = p

    def step(self, action: np.ndarray) -> EnvObservation:
        return self._observation(self._call("step", action=np.asarray(action)))

    def object_hidden_images(self) -> dict[str, np.ndarray]:
        """The env's object-hidden images of its current state, rendered in the server (one
        request for every camera)."""
        if not self.renders_hidden_objects:
            raise NotImplementedError(
                f"{self.entry} in the env server renders no object-hidden images "
                "(SuiteInfo.renders_hidden_objects is False)"
            )
        return dict(self._call("object_hidden_images"))

    def _observation(self, reply: dict[str, Any]) -> EnvObservation:
        self._generation += 1
        generation = self._generation

        def current() -> bool:
            return self._generation == generation

        images = LazyImages(self.cameras, lambda cam: self._call("render", camera=cam), current)
        privileged = (
            LazyState(lambda: self._call("privileged"), current)
            if reply["has_privileged"]
            else None
        )
        return EnvObservation(
            images=images,
            state=reply["state"],
            privileged=privileged,
            status=EpisodeStatus.from_wire(reply["status"]),
        )

    def close(self) -> None:
        """Idempotent."""
        server, self._server = self._server, None
        if server is not None:
            server.close()
