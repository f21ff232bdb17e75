"""The tiny VLA: a small vision-language-action policy in lerobot's format (type ``tiny_vla``),
registered with lerobot when ``lerobot_policy_idr`` is imported, so a robot computer with only
this plugin can load a tiny_vla checkpoint."""
