"""Backbones by kind; heavy modules are imported only when their kind is chosen."""

from __future__ import annotations

from typing import Any

from workers.backbones.base import Backbone
from workers.params_model import check_params
from workers.registry import load_class

BACKBONES: dict[str, str] = {
    "fake_marker": "workers.backbones.fakes:FakeMarkerBackbone",
    "noop": "workers.backbones.noop:NoopBackbone",
    "lerobot": "workers.backbones.lerobot.adapter:LerobotBackbone",
    # a policy server speaking openpi's websocket protocol (OpenVLA-OFT, openpi's JAX pi0.5...)
    "remote": "workers.backbones.websocket.client:WebsocketBackbone",
    # env-side: reads the tabletop env's privileged state
    "tabletop_expert": "workers.experts.tabletop:TabletopExpertBackbone",
}


def backbone_class(kind: str) -> Any:
    """The backbone class of ``kind`` (its module imported; no weights loaded)."""
    return load_class(BACKBONES, kind, "backbone.kind")


def check_backbone(kind: str, params: dict[str, Any]) -> None:
    """Validate kind and params without loading any weights (runs before actors start).

    Params must bind to the backbone's constructor; a backbone class may also define
    ``check_params(params)`` for checks of its own (a checkpoint path that does not exist)."""
    cls = backbone_class(kind)
    check_params(f"backbone.params (backbone {kind!r})", cls, params)
    if hasattr(cls, "check_params"):
        cls.check_params(params)


def make_backbone(kind: str, params: dict[str, Any]) -> Backbone:
    return backbone_class(kind)(**params)
