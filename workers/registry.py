"""Classes by name from a registry of "module:Class" strings, imported only when chosen, or
by an entry point "package.module:Class" given in the config itself.

Heavy modules (simulators, model code) are imported when their entry is picked, not when the
registry is read (lerobot's factory does the same); a wrong name gets a did-you-mean error
naming the config field.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
import warnings
from typing import Any

from workers import moved


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


def _moved(module: str, attr: str, field: str) -> tuple[str, str]:
    """An entry point of the flat layout (``workers.envs.tabletop:TabletopEnv``) mapped to where
    its class lives now, with a warning naming the new spelling."""
    for old in sorted(moved.MODULES, key=len, reverse=True):
        if module == old or module.startswith(old + "."):
            new_module = moved.MODULES[old] + module[len(old) :]
            head, _, rest = attr.partition(".")
            new_attr = moved.CLASSES.get(head, head) + (f".{rest}" if rest else "")
            warnings.warn(
                f"{field}: {module}:{attr} moved to {new_module}:{new_attr}; "
                "write the new name (docs/architecture.md#migration)",
                FutureWarning,
                stacklevel=3,
            )
            return new_module, new_attr
    return module, attr


def _entry_point(spec: str, field: str) -> Any:
    module, _, attr = spec.partition(":")
    if not module or not attr or ":" in attr:
        raise ValueError(f"{field}={spec!r}: an entry point is written 'package.module:Class'")
    module, attr = _moved(module, attr, field)
    try:
        mod = importlib.import_module(module)
    except Exception as e:  # ImportError, or a name Python cannot import (ValueError, ...)
        raise ValueError(
            f"{field}={spec!r}: cannot import module {module!r} ({e}); is it installed or on "
            "PYTHONPATH?"
        ) from None
    obj = mod
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"{field}={spec!r}: module {module!r} has no {attr!r}")
        obj = getattr(obj, part)
    if not inspect.isclass(obj):
        raise ValueError(f"{field}={spec!r} is not a class")
    return obj
