"""The tables a run's figures and HTML slices are drawn from, read once from its store: the
episodes, the steps joined with their episode's columns (per-inference progress), and the
effects across runs. No drawing here (pipeline.reporting.figures draws)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
from idr_core.refiner import RefinerConfig

from pipeline.results import aggregate as agg
from pipeline.results.calibration import read_calibration
from pipeline.results.store import RunStore
from pipeline.rundir import CONFIG_YAML

KEY = ["cell_id", "task_id", "episode_index"]


@dataclass
class RunData:
    """What the figures need from one run: episodes, per-inference rows with progress, tau labels."""

    episodes: pd.DataFrame  # the episodes table (error rows included)
    # per inference: KEY, step, e_img, e_prop, r_img, gate, grip (the gripper action) and from
    # its episode mode, strategy, alpha, suite, backbone, length, progress
    steps: pd.DataFrame
    tau_labels: dict[str, str]  # cell_id -> spelling of a calibrated tau ("calibrated*2")
    # the alpha the config declares for its cells (idr.alpha; else the refiner's default, the
    # paper's): a figure that shows one cell per mode picks the cell at it
    reference_alpha: float = field(default_factory=lambda: RefinerConfig().alpha)


EPISODE_COLUMNS = ["mode", "strategy", "alpha", "suite", "backbone"]  # joined onto each step


def progress_table(steps: pa.Table, episodes: pa.Table) -> pa.Table:
    """Steps joined with their episode (mode, strategy, alpha, suite, backbone, ``length``);
    ``progress`` = step / episode length, in [0, 1]. Error episodes (no outcome) are left out.

    An Arrow hash join: millions of step rows are joined without pandas' object-key merge (a
    5 M-row run: 2.3 s and most of the report's peak memory). Rows come in no set order."""
    ok = episodes.filter(pc.is_null(episodes["error"]))
    ok = ok.select([*KEY, *EPISODE_COLUMNS, "steps"]).rename_columns(
        [*KEY, *EPISODE_COLUMNS, "length"]
    )
    df = steps.join(ok, keys=KEY, join_type="inner")
    length = pc.cast(pc.max_element_wise(df["length"], 1), pa.float64())
    progress = pc.divide(pc.cast(df["step"], pa.float64()), length)
    progress = pc.min_element_wise(pc.max_element_wise(progress, 0.0), 1.0)
    return df.append_column("progress", progress)


def _last_elements(lists: pa.ChunkedArray) -> np.ndarray:
    """The last element of each list (NaN for a null or empty one), without a Python loop:
    the gripper dim of the executed action, read off the list column's flat values chunk by
    chunk (no copy of the whole column)."""
    parts = [np.zeros(0)]
    for arr in lists.chunks:
        if len(arr) == 0:
            continue
        offsets = arr.offsets.to_numpy()
        values = arr.values.to_numpy(zero_copy_only=False)
        ends = offsets[1:]
        ok = (ends > offsets[:-1]) & ~arr.is_null().to_numpy(zero_copy_only=False)
        out = np.full(len(arr), np.nan)
        out[ok] = values[ends[ok] - 1]
        parts.append(out)
    return np.concatenate(parts)


def declared_alpha(run_dir: str | Path) -> float:
    """``idr.alpha`` of RUN_DIR/config.yaml, else the refiner's default (the paper's)."""
    import yaml

    path = Path(run_dir) / CONFIG_YAML
    idr = (yaml.safe_load(path.read_text()) or {}).get("idr") if path.is_file() else None
    alpha = (idr or {}).get("alpha")
    return float(alpha) if alpha is not None else RefinerConfig().alpha


def backbone_label(run_dir: str | Path) -> str | None:
    """``kind`` or ``kind:<checkpoint folder name>`` from RUN_DIR/config.yaml: the episodes
    table says ``lerobot`` for every lerobot checkpoint, a heatmap row needs the model."""
    import yaml

    path = Path(run_dir) / CONFIG_YAML
    if not path.is_file():
        return None
    backbone = (yaml.safe_load(path.read_text()) or {}).get("backbone") or {}
    kind, ckpt = backbone.get("kind"), (backbone.get("params") or {}).get("path")
    if not kind:
        return None
    return f"{kind}:{Path(str(ckpt)).name}" if ckpt else str(kind)


def runs_effects(run_dirs: list[Path]) -> pd.DataFrame:
    """backbone, suite, e_img, e_prop of each run's reference diagnose cell (for the heatmap
    across runs); runs without a diagnose cell contribute nothing."""
    frames = []
    for run_dir in run_dirs:
        data = load_run(run_dir)
        ref = reference_diagnose(data.steps)
        if ref is not None:
            frames.append(
                data.steps.loc[
                    data.steps["cell_id"] == ref, ["backbone", "suite", "e_img", "e_prop"]
                ]
            )
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def load_run(run_dir: str | Path) -> RunData:
    store = RunStore(run_dir, read_only=True)
    episodes_table = store.episodes()
    episodes = episodes_table.to_pandas()
    cols = [*KEY, "step", "e_img", "e_prop", "r_img", "gate", "gripper"]
    table = store.steps(columns=cols)
    # the executed action (a list column, the bulk of the table) is only read where the env
    # does not name its gripper dim
    grip = table["gripper"].to_numpy(zero_copy_only=False).astype(float)
    if table.num_rows and np.isnan(grip).any():  # read again with it, the same rows in order
        table = store.steps(columns=[*cols, "action_final"])
        grip = table["gripper"].to_numpy(zero_copy_only=False).astype(float)
        grip = np.where(np.isnan(grip), _last_elements(table["action_final"]), grip)
        table = table.drop_columns(["action_final"])
    table = table.drop_columns(["gripper"]).append_column("grip", pa.array(grip))
    calib = read_calibration(run_dir) or {}
    labels = {cid: c["spec"] for cid, c in calib.get("cells", {}).items()}
    joined = progress_table(table, episodes_table)
    del table, episodes_table
    # column by column, each freed once converted: the Arrow copy and the frame are never
    # both whole in memory
    prog = joined.to_pandas(self_destruct=True, split_blocks=True)
    del joined
    label = backbone_label(run_dir)
    if label is not None:
        prog["backbone"] = label
    return RunData(episodes, prog, labels, declared_alpha(run_dir))


def reference_diagnose(frame: pd.DataFrame) -> str | None:
    """The diagnose cell whose effects stand for the baseline's (``frame``: rows with cell_id,
    mode, strategy): ``diagnose`` if present, else one with the paper's zero intervention,
    else the first by name."""
    cells = frame[frame["mode"] == "diagnose"].groupby("cell_id")["strategy"].first()
    if cells.empty:
        return None
    if "diagnose" in cells.index:
        return "diagnose"
    zero = sorted(cells.index[cells == "zero"])
    return str((zero or sorted(cells.index))[0])


EPS = agg.RIMG_EPS


MAX_EVENTS = 5  # k-th close / open events drawn, k <= this


def rimg_matrix(effects: pd.DataFrame) -> pd.DataFrame:
    """backbone x suite table of R_img = mean E_img / (mean E_img + mean E_prop + eps) (the
    paper's ratio of time averages, not the average of per-step ratios)."""
    effects = effects.dropna(subset=["e_img", "e_prop"])
    if "task_id" in effects and agg.any_perturbed(effects):
        # perturbed tasks: a column per suite x perturbation (the paper's observation 1: a
        # perturbed scene is another environment for the same policy)
        tagged = agg.with_perturbation(effects)
        effects = tagged.assign(suite=tagged["suite"].astype(str) + "\n" + tagged["perturbation"])
    g = effects.groupby(["backbone", "suite"])
    m = g[["e_img", "e_prop"]].mean()
    ratio = m["e_img"] / (m["e_img"] + m["e_prop"] + EPS)
    return ratio.unstack("suite").sort_index().sort_index(axis=1)


def gripper_events(steps: pd.DataFrame) -> dict[str, list[float]]:
    """Median normalized progress of the k-th gripper close and open event over episodes.

    An event is a sign change of the gripper action between consecutive inferences: to > 0 is
    a close, to <= 0 an open (+1 closes in LIBERO and robosuite); the k-th event of a kind is
    drawn when at least one episode has it, at its median progress. Vectorized over episodes
    (a diagnose cell of tens of thousands of episodes: no Python loop per episode)."""
    df = steps.dropna(subset=["grip"]).sort_values([*KEY, "step"])
    if df.empty:
        return {"close": [], "open": []}
    episode = df.groupby(KEY, sort=False).ngroup().to_numpy()
    closed = df["grip"].to_numpy() > 0
    at = np.flatnonzero((closed[1:] != closed[:-1]) & (episode[1:] == episode[:-1])) + 1
    events = pd.DataFrame(
        {
            "episode": episode[at],
            "kind": np.where(closed[at], "close", "open"),
            "progress": df["progress"].to_numpy()[at],
        }
    )
    events["k"] = events.groupby(["episode", "kind"]).cumcount() + 1
    medians = events[events["k"] <= MAX_EVENTS].groupby(["kind", "k"])["progress"].median()
    return {
        kind: [float(medians[(kind, k)]) for k in sorted(medians[kind].index)]
        if kind in medians.index.get_level_values(0)
        else []
        for kind in ("close", "open")
    }
