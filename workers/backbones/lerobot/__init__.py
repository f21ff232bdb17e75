"""lerobot policies as backbones."""

from workers.backbones.lerobot.adapter import LerobotBackbone
from workers.backbones.lerobot.checkpoint import check_checkpoint

__all__ = ["LerobotBackbone", "check_checkpoint"]
