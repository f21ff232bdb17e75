"""``Doc``: a constructor parameter's documentation, as ``Annotated`` metadata.

``image_size: Annotated[int, Doc("px per side")] = 96`` keeps a param's name, type, default
and documentation in one place; ``workers.params_model`` reads it for the docs' parameter
tables. Standard library only: env modules import it inside env servers whose interpreters
have neither pydantic nor typing_extensions.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Doc:
    """What the parameter means (one line of a parameter table)."""

    text: str
