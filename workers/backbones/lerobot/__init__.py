"""lerobot policies as backbones."""

from workers.backbones.lerobot.adapter import LerobotBackbone, check_checkpoint

__all__ = ["LerobotBackbone", "check_checkpoint"]
