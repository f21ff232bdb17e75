"""Per-episode hashes of a run's results: equal for equal tables whatever the timing, placement
or hardware label; a one-bit change in one step's action names that episode first."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config
from pipeline.results.digest import (
    episode_hashes,
    first_difference,
    hashed_columns,
    run_digest,
)

CONF = Path(__file__).resolve().parents[3] / "conf"


def _bump_first_action(run_dir: Path) -> str:
    """Flip the last bit of the first action value of one step file; returns its episode key."""
    f = sorted((run_dir / "steps").rglob("*.parquet"))[0]
    table = pq.read_table(f)
    df = table.to_pandas()
    row = df.sort_values(["cell_id", "task_id", "episode_index", "inference_index"]).index[0]
    actions = [np.array(a, dtype=np.float32) for a in df["action_final"]]
    a = actions[row].copy()
    a.view(np.uint32)[0] ^= 1
    actions[row] = a
    col = table.schema.get_field_index("action_final")
    table = table.set_column(
        col, "action_final", pa.array([x.tolist() for x in actions], table.schema.field(col).type)
    )
    pq.write_table(table, f)
    return f"{df.loc[row, 'cell_id']}/{df.loc[row, 'task_id']}/{df.loc[row, 'episode_index']}"


def test_hashes_ignore_timing_and_hardware_and_name_the_first_changed_episode(tmp_path) -> None:
    cfg = load_config(CONF / "smoke.yaml", ["executor.kind=inline", "tracking.enabled=false"])
    execute(plan_run(cfg, tmp_path / "a"))
    execute(plan_run(cfg, tmp_path / "b"))  # another execution: other times, run id, workers
    a, b = episode_hashes(tmp_path / "a"), episode_hashes(tmp_path / "b")
    assert len(a) == 12 and a == b and run_digest(a) == run_digest(b)
    assert first_difference(a, b) is None
    shutil.copytree(tmp_path / "a", tmp_path / "c")
    key = _bump_first_action(tmp_path / "c")
    c = episode_hashes(tmp_path / "c")
    assert first_difference(c, a) == f"{key}: differs"
    assert sum(c[k] != a[k] for k in a) == 1 and run_digest(c) != run_digest(a)
    assert first_difference({}, a).endswith("missing here")

    # a reference's recorded columns: a change outside them leaves its hashes, one inside not
    columns = hashed_columns()
    assert "action_final" in columns["steps"] and "run_id" not in columns["episodes"]
    older = {**columns, "steps": [n for n in columns["steps"] if n != "action_final"]}
    assert episode_hashes(tmp_path / "c", older) == episode_hashes(tmp_path / "a", older)
    assert episode_hashes(tmp_path / "c", columns) == c
    with pytest.raises(ValueError, match=r"steps table has no column\(s\) \['not_a_column'\]"):
        episode_hashes(tmp_path / "a", {**columns, "steps": ["not_a_column"]})
