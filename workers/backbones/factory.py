"""Backbones by kind; heavy modules are imported only when their kind is chosen."""

from __future__ import annotations

import difflib
import importlib
from typing import Any

from workers.backbones.base import Backbone

BACKBONES: dict[str, str] = {
    "fake_marker": "workers.backbones.fakes:FakeMarkerBackbone",
}


def check_backbone_kind(kind: str) -> None:
    if kind not in BACKBONES:
        close = difflib.get_close_matches(kind, list(BACKBONES), n=1)
        hint = f"did you mean {close[0]!r}?" if close else f"known: {sorted(BACKBONES)}"
        raise ValueError(f"backbone.kind={kind!r} is unknown; {hint}")


def make_backbone(kind: str, params: dict[str, Any]) -> Backbone:
    check_backbone_kind(kind)
    module, cls = BACKBONES[kind].split(":")
    return getattr(importlib.import_module(module), cls)(**params)
