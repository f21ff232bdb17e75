"""Hugging Face offline mode for the duration of a call, whatever was imported first.

``huggingface_hub`` reads ``HF_HUB_OFFLINE`` (or ``TRANSFORMERS_OFFLINE``) once, when it is first
imported, into ``huggingface_hub.constants.HF_HUB_OFFLINE``, and every request checks that
constant at call time (``is_offline_mode()``; transformers and lerobot ask it too); ``datasets``
copies it into ``datasets.config`` on its own import. ``idr-eval``'s CLI sets the variables before
anything imports them; a training loop or a notebook has usually imported them already, and
without the flag a checkpoint that names a sub-model by hub id (SmolVLA's VLM) retries the hub
for minutes before it loads from the cache. :func:`hf_offline` therefore sets both: the
variables (read by child processes, a local Ray's actors, a library imported later) and the
constants already imported, and puts everything back on exit. A user's own setting stands
(``HF_HUB_OFFLINE=0`` allows downloads), as in the CLI.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

#: the variables the CLI sets (pipeline/cli.py), with the value it gives them
OFFLINE_ENV = {"HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1", "TRANSFORMERS_OFFLINE": "1"}

_TRUE = {"1", "ON", "YES", "TRUE"}


def _true(value: str | None) -> bool:
    return value is not None and value.upper() in _TRUE


def _library_flags() -> dict[tuple[str, str], bool]:
    """What each library that reads a flag at import would have read from the environment now
    (module, attribute) -> value, by the library's own rule."""
    hub = _true(os.environ.get("HF_HUB_OFFLINE") or os.environ.get("TRANSFORMERS_OFFLINE"))
    datasets = os.environ.get("HF_DATASETS_OFFLINE")
    ds = hub if datasets is None else _true(datasets)
    return {
        ("huggingface_hub.constants", "HF_HUB_OFFLINE"): hub,
        ("datasets.config", "HF_HUB_OFFLINE"): ds,
        ("datasets.config", "HF_DATASETS_OFFLINE"): ds,
    }


def apply_env_to_libraries() -> None:
    """Set the flags of the libraries already imported from the environment as it is now."""
    for (module, attr), value in _library_flags().items():
        mod = sys.modules.get(module)
        if mod is not None and hasattr(mod, attr):
            setattr(mod, attr, value)


@contextmanager
def hf_offline() -> Iterator[None]:
    """Offline for the block (unless the user's environment says otherwise), restored after."""
    saved_env = {k: os.environ.get(k) for k in OFFLINE_ENV}
    saved_attrs: dict[tuple[str, str], Any] = {}
    for module, attr in _library_flags():
        mod = sys.modules.get(module)
        if mod is not None and hasattr(mod, attr):
            saved_attrs[(module, attr)] = getattr(mod, attr)
    for key, value in OFFLINE_ENV.items():
        os.environ.setdefault(key, value)
    apply_env_to_libraries()
    try:
        yield
    finally:
        for key, value in saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        # a library imported during the block read the block's variables: it gets what it
        # would have read without them; one imported before gets its own value back
        apply_env_to_libraries()
        for (module, attr), value in saved_attrs.items():
            setattr(sys.modules[module], attr, value)
