"""idr_core's feature keys are lerobot's, and its tensor check tells torch from numpy."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from idr_core import features
from idr_core.tensors import is_torch
from lerobot.utils import constants

SHARED = (
    "OBS_PREFIX",
    "OBS_STATE",
    "OBS_ENV_STATE",
    "OBS_IMAGE",
    "OBS_IMAGES",
    "OBS_LANGUAGE_TOKENS",
    "OBS_LANGUAGE_ATTENTION_MASK",
    "ACTION",
)


@pytest.mark.parametrize("name", SHARED)
def test_each_key_is_lerobots_of_the_same_name(name) -> None:
    assert getattr(features, name) == getattr(constants, name)


def test_every_key_of_ours_is_checked_or_built_from_a_checked_one() -> None:
    ours = {n for n in vars(features) if n.isupper()}
    assert ours - set(SHARED) == {"IMAGE_PREFIX", "SINGLE_CAMERA"}
    assert features.IMAGE_PREFIX == constants.OBS_IMAGES + "."


@pytest.mark.parametrize(
    ("key", "camera"),
    [
        ("observation.images.wrist", "wrist"),
        ("observation.images.cam_high", "cam_high"),
        ("observation.image", "image"),  # lerobot's one-camera key (PushT)
        ("observation.state", None),
        ("observation.images", None),  # the stacked cameras, not one camera's key
        ("observation.image_features", None),
        ("action", None),
    ],
)
def test_a_camera_is_read_off_its_key(key, camera) -> None:
    assert features.camera_of(key) == camera
    assert features.is_image_key(key) == (camera is not None)


def test_is_torch_tells_a_tensor_from_an_array_and_a_number() -> None:
    assert is_torch(torch.zeros(2)) and is_torch(torch.nn.Parameter(torch.zeros(2)))
    assert not any(is_torch(x) for x in (np.zeros(2), np.float32(1.0), 1.0, [torch.zeros(1)]))
