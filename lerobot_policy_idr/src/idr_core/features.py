"""The keys of a lerobot batch and checkpoint's features (``observation.state``, a camera's
``observation.images.<cam>``, ``action``), in one place for the harness and the plugin alike.

The values are lerobot's (``lerobot.utils.constants``, of the same names; a test checks they
are equal). They are written out here because importing lerobot loads torch, and ``idr_core``
imports neither.
"""

from __future__ import annotations

OBS_PREFIX = "observation."
OBS_STATE = "observation.state"
OBS_ENV_STATE = "observation.environment_state"
#: lerobot's one-camera key (PushT's checkpoints); the harness names its camera "image"
OBS_IMAGE = "observation.image"
#: the cameras stacked into one tensor (what a queue-fed base's queues hold)
OBS_IMAGES = "observation.images"
#: a camera's key is ``IMAGE_PREFIX + camera``
IMAGE_PREFIX = OBS_IMAGES + "."
OBS_LANGUAGE_TOKENS = "observation.language.tokens"
OBS_LANGUAGE_ATTENTION_MASK = "observation.language.attention_mask"
ACTION = "action"

#: the camera ``OBS_IMAGE`` stands for
SINGLE_CAMERA = "image"


def is_image_key(key: str) -> bool:
    """A camera's key: ``observation.images.<cam>``, or lerobot's one-camera
    ``observation.image``."""
    return key == OBS_IMAGE or key.startswith(IMAGE_PREFIX)


def camera_of(key: str) -> str | None:
    """The camera a feature key reads (``observation.images.wrist`` -> ``wrist``,
    ``observation.image`` -> ``image``), or None for a key that is not a camera's."""
    if key.startswith(IMAGE_PREFIX):
        return key.removeprefix(IMAGE_PREFIX)
    return SINGLE_CAMERA if key == OBS_IMAGE else None
