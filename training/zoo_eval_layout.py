"""Where the evaluator of a training run keeps what it writes, where each benchmark's held-out
frames and closed-loop config are, and which saved checkpoints are whole
(``training.zoo_evaluator``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    pass

EVALS = "evals"  # RUN/evals: everything the evaluator writes
LEDGER = "evals.jsonl"
RUN_ID_FILE = "mlflow_run_id"
CURRENT = "current.json"  # the step being evaluated; left behind only by a killed evaluator
ENDED = "training_ended"  # written by `zoo train` when lerobot-train has exited
LOG = "evaluator.log"
LOCK = "evaluator.lock"
EXPERIMENT = "zoo-training"
STABLE_S = 2.0  # a checkpoint folder unchanged this long is whole (lerobot writes file by file)
EXIT_LOCKED = 3  # another evaluator holds the run: not restarted
MAX_RESTARTS = 3  # evaluators restarted after dying while training runs (a crash loop stops)
CONTROL = "@image_blackout"  # the image-zeroed control task (pipeline.results.observation_stats)

# held-out demonstrations per benchmark, recorded from init states no member trained on (the
# training demonstrations use tabletop episodes 100000-300029, MetaWorld's from 100000)
TABLETOP_HELDOUT = (
    "python -m training.tabletop_demos --root data/zoo/tabletop_heldout --episodes 8 "
    "--tasks pick_color stack_color --first-episode 400000"
)
HELDOUT: dict[str, tuple[Path, str]] = {
    "tabletop": (Path("data/zoo/tabletop_heldout"), TABLETOP_HELDOUT),
    "tabletop_pos": (
        Path("data/zoo/tabletop_pos_heldout"),
        f"{TABLETOP_HELDOUT} && python -m training.zoo_state --src data/zoo/tabletop_heldout "
        "--dst data/zoo/tabletop_pos_heldout",
    ),
    "metaworld": (
        Path("data/zoo/metaworld_heldout"),
        "python -m training.metaworld_demos --root data/zoo/metaworld_heldout --episodes 8 "
        "--first-episode 200000",
    ),
}
# the closed-loop cell: the benchmark's zoo config and what makes it fit the benchmark's members
CLOSED_LOOP_CONFIG = {
    "tabletop": ("conf/zoo/tabletop.yaml", ()),
    "tabletop_pos": ("conf/zoo/tabletop.yaml", ("env.params.state_dims=[0,1,2,6,7]",)),
    "metaworld": ("conf/zoo/metaworld.yaml", ()),
}

#: one evaluation: (step, the checkpoint's pretrained_model folder) -> {"ran": [...],
#: "metrics": {...}, "errors": {part: message}}; an exception is an error of the whole step
EvaluateFn = Callable[[int, Path], dict[str, Any]]


# --- checkpoints -----------------------------------------------------------------------------


def saved_checkpoints(run: Path) -> dict[int, Path]:
    """The step folders under ``RUN/checkpoints`` (``000200``, ...; not ``last``), by step."""
    folder = run / "checkpoints"
    if not folder.is_dir():
        return {}
    return {int(p.name): p for p in folder.iterdir() if p.name.isdigit() and p.is_dir()}


def checkpoint_state(step_dir: Path, stable_s: float = STABLE_S, now: float | None = None) -> str:
    """``ready`` (config.json and model.safetensors there, nothing changed for ``stable_s``),
    ``writing`` (something changed within ``stable_s``) or ``incomplete`` (files missing, nothing
    changing: a save cut short, or one not begun)."""
    now = time.time() if now is None else now
    try:
        newest = max([step_dir.stat().st_mtime, *(p.stat().st_mtime for p in step_dir.rglob("*"))])
    except FileNotFoundError:  # a file replaced while listed: being written
        return "writing"
    if now - newest < stable_s:
        return "writing"
    model = step_dir / "pretrained_model"
    whole = (model / "config.json").is_file() and (model / "model.safetensors").is_file()
    return "ready" if whole else "incomplete"


def log(message: str) -> None:
    print(f"[zoo_evaluator {time.strftime('%H:%M:%S')}] {message}", flush=True)
