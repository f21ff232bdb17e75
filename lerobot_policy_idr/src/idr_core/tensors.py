"""Whether a value is a torch tensor, asked without importing torch (so numpy-only callers
never load it)."""

from __future__ import annotations

from typing import Any


def is_torch(x: Any) -> bool:
    """True for a torch tensor (or any object of a ``torch`` module): the array code here takes
    numpy and torch alike and branches on this."""
    return type(x).__module__.startswith("torch")
