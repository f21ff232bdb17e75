"""What an env gives a policy and what a checkpoint asks for, known without a simulator or weights.

The driver reads both before any actor starts (``pipeline.planning.checkpoint_fit`` matches them): an env from its
params (``describe`` classmethod), a checkpoint from its ``config.json``. A mismatch (a camera the
env does not have, another image size, state or action dims) is refused there, naming both sides.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Literal

# Names under which policies know robosuite's two standard cameras, by convention:
# lerobot's LIBERO datasets (image, image2), openpi's converted LIBERO data (image, wrist_image),
# robosuite's own observation keys, and other checkpoints' (front / wrist).
AGENTVIEW_ALIASES: tuple[str, ...] = ("agentview", "image", "agentview_image", "front", "main")
WRIST_ALIASES: tuple[str, ...] = (
    "wrist",
    "image2",
    "wrist_image",
    "robot0_eye_in_hand_image",
    "eye_in_hand",
)
ROBOSUITE_CAMERA_ALIASES: Mapping[str, tuple[str, ...]] = {
    "agentview": AGENTVIEW_ALIASES,
    "wrist": WRIST_ALIASES,
}

Replan = int | Literal["chunk"]


@dataclass(frozen=True)
class EnvIO:
    """What an env built from given params renders and accepts."""

    cameras: tuple[str, ...]  # the ones it renders with these params
    image_size: int  # square images, in px, unless the checkpoint decides (below)
    state_dim: int
    action_dim: int
    # env camera -> other names a checkpoint may give it (its own name always matches)
    camera_aliases: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    # True: the image size was left to the checkpoint (the protocol renders at its size)
    image_size_from_checkpoint: bool = False
    # actions executed per inference under the env's protocol; None: the env pins none
    replan: Replan | None = None
    # the pinned protocol, logged with the run and shown in the report ({}: none)
    protocol: Mapping[str, object] = field(default_factory=dict)
    # cameras rendered at another size than image_size: square px (CALVIN: static 200, gripper
    # 84) or (height, width) for a camera that is not square (ALOHA: 480x640)
    camera_sizes: Mapping[str, int | tuple[int, int]] = field(default_factory=dict)
    # an env that renders no camera with these params: the setting that makes it render some
    # (a lerobot plugin's ``image_obs``), named when a mode needs an image; None: none known
    image_option: str | None = None

    def hw_of(self, camera: str) -> tuple[int, int]:
        """The (height, width) ``camera`` renders at."""
        size = self.camera_sizes.get(camera, self.image_size)
        return (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))

    def size_label(self, camera: str) -> str:
        h, w = self.hw_of(camera)
        return str(h) if h == w else f"{h}x{w}"


@dataclass(frozen=True)
class PolicyIO:
    """What a checkpoint declares it reads and writes (from its config.json)."""

    images: Mapping[str, tuple[int, ...]]  # image key suffix (observation.images.<k>) -> (C, H, W)
    state_dim: int | None  # None: reads no state
    action_dim: int
    chunk_len: int  # actions of each predicted chunk it executes (n_action_steps)
    resizes_images: bool  # resizes any image to its own resolution (pi0, pi0.5, SmolVLA...)
    source: str  # where this was read, for messages
    # False: images and state_dim are not declared (a policy server's metadata names neither),
    # so empty / None say nothing about what it reads
    declares_inputs: bool = True
    # whether inference samples (its draws differ under other noise): False for deterministic
    # policies (ACT, the tiny VLA), None where unknown
    samples: bool | None = None
    # the mean state of its training data, physical units (do(S) under state_space=centered),
    # and where it was read; None with trained_on_data: a checkpoint that should hold one and
    # does not
    state_mean: tuple[float, ...] | None = None
    state_mean_source: str | None = None
    trained_on_data: bool = False
