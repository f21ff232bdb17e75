"""The tiny VLA: a small vision-language-action policy in lerobot's format (type ``tiny_vla``)."""
