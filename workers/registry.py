"""Classes by name from a registry of "module:Class" strings, imported only when chosen, or
by an entry point "package.module:Class" given in the config itself.

Heavy modules (simulators, model code) are imported when their entry is picked, not when the
registry is read (lerobot's factory does the same); a wrong name gets a did-you-mean error
naming the config field, and an entry point written for the old flat layout of workers/ gets an
error naming the one to write.
"""

from __future__ import annotations

import difflib
import importlib
import importlib.util
import inspect
from typing import Any

# Where modules went when workers/ was laid out by concern: only the data of the refusal of an
# entry point copied from the old layout (configs name suites and backbones by registry name).
MOVED_MODULES: dict[str, str] = {
    "workers.actor": "workers.episode.worker",
    "workers.episode": "workers.episode.rows",  # a package now: mapped when named exactly
    "workers.forward_shape": "workers.policy.forward_shape",
    "workers.idr_wrapper": "workers.policy.wrapper",
    "workers.observation": "workers.episode.observation",
    "workers.policy_actor": "workers.policy.actor",
    "workers.policy_service": "workers.policy.service",
    "workers.policy_socket": "workers.policy.socket_server",  # split: see MOVED_CLASSES
    "workers.videos": "workers.episode.videos",
    "workers.backbones.remote": "workers.backbones.websocket",
    "workers.envs.calvin": "workers.envs.suites.calvin.env",
    "workers.envs.libero": "workers.envs.suites.libero.env",
    "workers.envs.libero_assets": "workers.envs.suites.libero.assets",
    "workers.envs.libero_protocol": "workers.envs.suites.libero.protocol",
    "workers.envs.perturbations": "workers.envs.wrappers.perturbations",
    "workers.envs.remote": "workers.envs.server.client",
    "workers.envs.server": "workers.envs.server.serve",
    "workers.envs.simpler": "workers.envs.suites.simpler.env",
    "workers.envs.simpler_protocol": "workers.envs.suites.simpler.protocol",
    "workers.envs.stability": "workers.envs.mujoco.stability",
    "workers.envs.tabletop": "workers.envs.suites.tabletop.env",
    "workers.envs.tabletop_layout": "workers.envs.suites.tabletop.layout",
    "workers.envs.tabletop_sim": "workers.envs.suites.tabletop.sim",
    "workers.envs.vulkan_cpu": "workers.envs.suites.simpler.vulkan_cpu",
    "workers.envs.wire": "workers.envs.server.wire",
}
# classes of a module split in the move that went elsewhere than the module's MOVED_MODULES heir
# ("old.module:Class" -> new module)
MOVED_CLASSES: dict[str, str] = {
    "workers.policy_socket:PolicyEndpoint": "workers.policy.socket_settings",
    "workers.policy_socket:PolicyServiceError": "workers.policy.socket_client",
    "workers.policy_socket:PolicySocketConnection": "workers.policy.socket_client",
    "workers.policy_socket:SocketLimits": "workers.policy.socket_settings",
    "workers.policy_socket:SocketSettings": "workers.policy.socket_settings",
    "workers.policy_socket:SocketToken": "workers.policy.socket_settings",
}
# classes renamed in the move (old name -> new name)
RENAMED_CLASSES: dict[str, str] = {
    "RemoteEnv": "EnvServerClient",
    "RemoteBackbone": "WebsocketBackbone",
    "RemotePolicy": "PolicyServiceClient",
}


def load_class(registry: dict[str, str], name: str, field: str) -> Any:
    """The class registered as ``name``, or named by an entry point ``"package.module:Class"``
    (Gymnasium style: a class of one's own, a test double, without registering it)."""
    if ":" in name:
        return _entry_point(name, field)
    if name not in registry:
        close = difflib.get_close_matches(name, list(registry), n=1)
        hint = f"did you mean {close[0]!r}?" if close else f"known: {sorted(registry)}"
        raise ValueError(
            f"{field}={name!r} is unknown; {hint} (or give a class as 'package.module:Class')"
        )
    return _entry_point(registry[name], field)


def _retired(module: str, attr: str, *, importable: bool) -> str | None:
    """Where an entry point of the flat layout (``workers.envs.tabletop:TabletopEnv``) lives now,
    or None when it names nothing that moved. Asked only once the entry point has failed, so a
    path of the present layout is never refused. A module that still imports (the packages
    ``workers.envs.server``, ``workers.episode``) is mapped only when named exactly, not its
    submodules; a class of a module split in the move goes where MOVED_CLASSES says."""
    if module != "workers" and not module.startswith("workers."):
        return None  # a class of one's own: its names are not ours to map
    new_module = module
    for old in sorted(MOVED_MODULES, key=len, reverse=True):
        if module == old or (not importable and module.startswith(old + ".")):
            new_module = MOVED_MODULES[old] + module[len(old) :]
            break
    head, _, rest = attr.partition(".")
    new_module = MOVED_CLASSES.get(f"{module}:{head}", new_module)
    new_attr = RENAMED_CLASSES.get(head, head) + (f".{rest}" if rest else "")
    if (new_module, new_attr) == (module, attr):
        return None
    try:
        if importlib.util.find_spec(new_module) is None:
            return None
    except ImportError:
        return None
    return f"{new_module}:{new_attr}"


def _refuse_retired(spec: str, field: str, *, importable: bool) -> None:
    module, _, attr = spec.partition(":")
    new = _retired(module, attr, importable=importable)
    if new is not None:
        raise ValueError(
            f"{field}={spec!r} names the old layout of workers/; write {field}: {new} "
            "(docs/architecture.md#migration)"
        )


def _entry_point(spec: str, field: str) -> Any:
    module, _, attr = spec.partition(":")
    if not module or not attr or ":" in attr:
        raise ValueError(f"{field}={spec!r}: an entry point is written 'package.module:Class'")
    try:
        mod = importlib.import_module(module)
    except Exception as e:  # ImportError, or a name Python cannot import (ValueError, ...)
        _refuse_retired(spec, field, importable=False)
        raise ValueError(
            f"{field}={spec!r}: cannot import module {module!r} ({e}); is it installed or on "
            "PYTHONPATH?"
        ) from None
    obj = mod
    for part in attr.split("."):
        if not hasattr(obj, part):
            _refuse_retired(spec, field, importable=True)
            raise ValueError(f"{field}={spec!r}: module {module!r} has no {attr!r}")
        obj = getattr(obj, part)
    if not inspect.isclass(obj):
        raise ValueError(f"{field}={spec!r} is not a class")
    return obj
