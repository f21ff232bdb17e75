"""Backbones by kind; heavy modules are imported only when their kind is chosen."""

from __future__ import annotations

import difflib
import importlib
import inspect
from typing import Any

from workers.backbones.base import Backbone

BACKBONES: dict[str, str] = {
    "fake_marker": "workers.backbones.fakes:FakeMarkerBackbone",
    "noop": "workers.backbones.noop:NoopBackbone",
    "lerobot": "workers.backbones.lerobot.adapter:LerobotBackbone",
    # env-side: reads the tabletop env's privileged state
    "tabletop_expert": "workers.envs.tabletop_experts:TabletopExpertBackbone",
}


def check_backbone_kind(kind: str) -> None:
    if kind not in BACKBONES:
        close = difflib.get_close_matches(kind, list(BACKBONES), n=1)
        hint = f"did you mean {close[0]!r}?" if close else f"known: {sorted(BACKBONES)}"
        raise ValueError(f"backbone.kind={kind!r} is unknown; {hint}")


def _cls(kind: str) -> Any:
    check_backbone_kind(kind)
    module, cls = BACKBONES[kind].split(":")
    return getattr(importlib.import_module(module), cls)


def check_backbone(kind: str, params: dict[str, Any]) -> None:
    """Validate kind and params without loading any weights (runs before actors start).

    Params must bind to the backbone's constructor; a backbone class may also define
    ``check_params(params)`` for checks of its own (a checkpoint path that does not exist)."""
    cls = _cls(kind)
    check_params_bind(f"backbone.params (backbone {kind!r})", cls, params)
    if hasattr(cls, "check_params"):
        cls.check_params(params)


def check_params_bind(where: str, cls: Any, params: dict[str, Any]) -> None:
    sig = inspect.signature(cls)
    try:
        sig.bind(**params)
    except TypeError as e:
        accepted = [n for n in sig.parameters if n != "self"]
        raise ValueError(f"{where}: {e}; accepted parameters: {accepted}") from None


def make_backbone(kind: str, params: dict[str, Any]) -> Backbone:
    return _cls(kind)(**params)
