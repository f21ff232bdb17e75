"""Where and how an env server runs: the two settings the driver resolves and an actor needs,
kept apart from the socket client so that the driver/actor contract (``workers.episode.rows``)
imports no process or socket code."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ServerSpec:
    """Where and how an env server runs (``env.python`` / ``env.server_timeout_s``)."""

    python: str  # the interpreter (absolute path once the driver resolved it)
    timeout_s: float = 120.0  # a request (or the start and build) longer than this: killed
