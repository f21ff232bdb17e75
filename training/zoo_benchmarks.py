"""The zoo's benchmarks: where each one's dataset, training runs and exported checkpoints live,
the features its members are trained on, and the offline environment lerobot-train and the
evaluator run in (``training.zoo``, ``training.zoo_evaluator``)."""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

from idr_core.features import ACTION, IMAGE_PREFIX, OBS_IMAGE, OBS_STATE

ROOT = Path(__file__).resolve().parents[1]
DATASET = Path("data/zoo/tabletop")
RUNS = Path("data/zoo/runs")
SHIPPED = Path("checkpoints/zoo")

# the features every member is trained on: the tabletop suite's two cameras at 96 px, its 8-d
# state and 7-d end-effector action (training/tabletop_demos.py writes them)
TABLETOP_FEATURES = {
    f"{IMAGE_PREFIX}agentview": [96, 96, 3],
    f"{IMAGE_PREFIX}wrist": [96, 96, 3],
    OBS_STATE: [8],
    ACTION: [7],
}
# the same demonstrations with the state's orientation left out (training/zoo_state.py: the dims a
# policy can copy the last action from, which the tiny VLA masks with a flag and lerobot's
# architectures cannot); evaluated with the tabletop suite's env.params.state_dims=[0,1,2,6,7]
TABLETOP_POS_FEATURES = {**TABLETOP_FEATURES, OBS_STATE: [5]}
# MetaWorld at 96 px (conf/zoo/metaworld.yaml; training/metaworld_demos.py): one camera, the
# hand's position and gripper, a 4-d action
METAWORLD_FEATURES = {
    OBS_IMAGE: [96, 96, 3],
    OBS_STATE: [4],
    ACTION: [4],
}


@dataclass(frozen=True)
class Benchmark:
    """Where a benchmark's dataset, training runs and exported checkpoints live."""

    dataset: Path
    features: dict[str, list[int]]
    runs: Path
    shipped: Path
    record: str  # the command that records its dataset


BENCHMARKS = {
    "tabletop": Benchmark(
        DATASET, TABLETOP_FEATURES, RUNS, SHIPPED, "bash scripts/record_zoo_data.sh"
    ),
    "tabletop_pos": Benchmark(
        Path("data/zoo/tabletop_pos"),
        TABLETOP_POS_FEATURES,
        RUNS / "tabletop_pos",
        SHIPPED / "tabletop_pos",
        "bash scripts/record_zoo_data.sh && python -m training.zoo_state",
    ),
    "metaworld": Benchmark(
        Path("data/zoo/metaworld"),
        METAWORLD_FEATURES,
        RUNS / "metaworld",
        SHIPPED / "metaworld",
        "python -m training.metaworld_demos --root data/zoo/metaworld --episodes 30",
    ),
}


def offline_env(threads: int) -> dict[str, str]:
    env = dict(os.environ)
    env.update(
        HF_HUB_OFFLINE="1",
        HF_DATASETS_OFFLINE="1",
        TRANSFORMERS_OFFLINE="1",
        OMP_NUM_THREADS=str(threads),
        MKL_NUM_THREADS=str(threads),
    )
    return env


def run_dir(name: str, seed: int, runs: Path = RUNS, init_from: Path | None = None) -> Path:
    """The run folder: ``NAME_seedS``, or ``NAME_seedS_continued`` for a stage that starts from an
    exported checkpoint's weights (so it neither resumes nor overwrites the first stage's run)."""
    return runs / (f"{name}_seed{seed}" + ("_continued" if init_from is not None else ""))


def last_checkpoint(out: Path) -> Path | None:
    last = out / "checkpoints" / "last"
    return last if (last / "pretrained_model" / "config.json").is_file() else None
