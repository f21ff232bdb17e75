"""Third-party lerobot plugins that fail to import, named with their own error.

lerobot's ``register_third_party_plugins`` imports every installed ``lerobot_policy_*``
distribution and only logs one that raises; a policy type that plugin registers then reads as
unknown. The plugin's own error, with its name, is what tells a user what to fix.
"""

from __future__ import annotations

import importlib
import importlib.metadata

POLICY_PLUGIN_PREFIX = "lerobot_policy_"  # lerobot's rule: the distribution's name, underscores


def policy_plugins() -> list[str]:
    """The installed policy plugins' distribution names, which are their import names."""
    names = {d.metadata.get("Name") or "" for d in importlib.metadata.distributions()}
    return sorted(n for n in names if n.startswith(POLICY_PLUGIN_PREFIX))


def import_error(module: str) -> str | None:
    """``module``'s import error as ``Type: message``; None when it imports."""
    try:
        importlib.import_module(module)
    except Exception as e:  # a plugin may raise anything at import; report it, do not crash
        return f"{type(e).__name__}: {e}"
    return None


def plugin_import_errors() -> dict[str, str]:
    """Each installed policy plugin that fails to import, with its error."""
    return {name: err for name in policy_plugins() if (err := import_error(name)) is not None}


def describe_failures(errors: dict[str, str]) -> str:
    """A sentence naming each plugin that failed and its error ('' when none did)."""
    if not errors:
        return ""
    parts = "; ".join(f"{name} raised {err}" for name, err in sorted(errors.items()))
    return f"; installed plugins that fail to import (fix or reinstall them): {parts}"
