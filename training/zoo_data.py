"""The zoo's dataset: merge recorded LeRobotDataset parts into the one dataset ``lerobot-train``
reads, and read its task instructions (the vocabulary, tokenizers and VLM files are built from
them).

``scripts/record_zoo_data.sh`` records the zoo's tabletop demonstrations in parts (expert, DART
and DAgger-labelled episodes, two recorders at a time on two cores) with
``training/tabletop_demos.py``; this joins them with lerobot's own ``merge_datasets`` so that
``lerobot-train --dataset.root=data/zoo/tabletop`` trains every zoo architecture on the same
frames.

    python -m training.zoo_data --out data/zoo/tabletop data/zoo/parts/*
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path


def merge(parts: list[Path], out: Path, repo_id: str = "local/zoo_tabletop") -> dict:
    """Merge ``parts`` (LeRobotDataset roots with equal features) into ``out``; returns a summary."""
    from lerobot.datasets.dataset_tools import merge_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    missing = [str(p) for p in parts if not (p / "meta" / "info.json").is_file()]
    if missing:
        raise SystemExit(f"not a recorded dataset (no meta/info.json): {missing}")
    datasets = [LeRobotDataset(repo_id=f"local/{p.name}", root=p) for p in parts]
    features = {p: ds.meta.features for p, ds in zip(parts, datasets, strict=True)}
    first = next(iter(features.values()))
    for p, f in features.items():
        if f != first:
            raise SystemExit(f"{p} has other features than {parts[0]}; record them alike")
    if out.exists():
        shutil.rmtree(out)
    merged = merge_datasets(datasets, output_repo_id=repo_id, output_dir=out)
    summary = {
        "episodes": merged.meta.total_episodes,
        "frames": merged.meta.total_frames,
        "tasks": sorted(merged.meta.tasks.index.tolist()),
        "parts": {p.name: ds.meta.total_episodes for p, ds in zip(parts, datasets, strict=True)},
    }
    (out / "meta" / "zoo_parts.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def dataset_tasks(root: Path) -> list[str]:
    """The task instructions of the LeRobotDataset at ``root``, sorted."""
    import pandas as pd

    return sorted(pd.read_parquet(root / "meta" / "tasks.parquet").index.astype(str))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--repo-id", default="local/zoo_tabletop")
    ap.add_argument("parts", type=Path, nargs="+")
    args = ap.parse_args()
    print(json.dumps(merge(args.parts, args.out, args.repo_id), indent=2))


if __name__ == "__main__":
    main()
