"""A zoo dataset with its cameras encoded as AV1 video, small enough to carry to a GPU machine.

The zoo's datasets store every frame as a PNG (about 7.7 KB per 96 px camera frame: 471 MB for
the tabletop's 30,636 frames of two cameras). lerobot's own conversion
(``convert_image_to_video_dataset``, what ``lerobot-edit-dataset --operation.type
convert_image_to_video`` runs) encodes them as AV1 at about 0.26 KB per frame (16 MB) with a
keyframe every 40 frames. Two things it leaves out are put back: the cameras' entries in
``meta/stats.json`` (lerobot-train reads them; the members normalize images with ImageNet's
statistics, which lerobot writes over them, so the checkpoint's normalizer is the same either
way) and ``meta/zoo_parts.json`` (the model card's list of parts).

AV1 at crf 30 is lossy: a member trained on the video sees frames a little off the renderer's
(as lerobot's hub datasets are), then is evaluated on the renderer's own frames.

    python -m training.zoo_video --src data/zoo/tabletop_pos --dst data/zoo/tabletop_pos_video
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
from pathlib import Path

from idr_core.features import OBS_IMAGE

GOP = 40  # frames between keyframes: a sample decodes at most this many frames per camera
PRESET = 8  # SVT-AV1's speed preset (lerobot's default 12 is the fastest and largest)
CRF = 30  # lerobot's default quality


def convert(src: Path, dst: Path, workers: int = 1) -> Path:
    from lerobot.configs.video import rgb_encoder_defaults
    from lerobot.datasets.dataset_tools import convert_image_to_video_dataset
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    if dst.exists():
        raise SystemExit(f"--dst {dst} exists: remove it or name another folder")
    source = LeRobotDataset("local/zoo", root=src)
    encoder = dataclasses.replace(rgb_encoder_defaults(), g=GOP, preset=PRESET, crf=CRF)
    convert_image_to_video_dataset(
        source, output_dir=dst, repo_id="local/zoo_video", rgb_encoder=encoder, num_workers=workers
    )
    stats_in = json.loads((src / "meta" / "stats.json").read_text())
    stats_path = dst / "meta" / "stats.json"
    stats = json.loads(stats_path.read_text())
    stats.update({k: v for k, v in stats_in.items() if k.startswith(OBS_IMAGE)})
    stats_path.write_text(json.dumps(stats, indent=4))
    parts = src / "meta" / "zoo_parts.json"
    if parts.is_file():
        shutil.copy2(parts, dst / "meta" / "zoo_parts.json")
    return dst


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", type=Path, default=Path("data/zoo/tabletop_pos"))
    ap.add_argument("--dst", type=Path, default=Path("data/zoo/tabletop_pos_video"))
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args(argv)
    print(convert(args.src, args.dst, args.workers))


if __name__ == "__main__":
    main()
