"""The interventions do(V = v*) and do(S = s*) as the harness imports them; the implementation
is ``idr_core.interventions`` (shared with the lerobot policy type ``idr``)."""

from idr_core.interventions import (
    SPACES,
    STRATEGIES,
    InterventionConfig,
    Space,
    Strategy,
    intervene,
    intervene_about,
)

__all__ = [
    "SPACES",
    "STRATEGIES",
    "InterventionConfig",
    "Space",
    "Strategy",
    "intervene",
    "intervene_about",
]
