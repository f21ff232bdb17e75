"""The report's header: the env protocol a run used, read from run.json."""

from __future__ import annotations

import json

from pipeline.reporting.markdown import build_report, protocol_line
from pipeline.results.store import RunStore
from tests.doubles.rows import result


def test_the_report_names_the_protocol_of_the_run(tmp_path) -> None:
    RunStore(tmp_path).write([result({"success": True, "steps": 3})])
    assert "Env protocol" not in build_report(tmp_path)  # a run of an env without one
    protocol = {"name": "lerobot", "seed": "seed + episode", "max_steps": {"libero_spatial": 280}}
    (tmp_path / "run.json").write_text(json.dumps({"run_id": "r", "protocol": protocol}))
    text = build_report(tmp_path)
    assert "Env protocol: lerobot (seed seed + episode, max_steps {'libero_spatial': 280})." in text
    assert protocol_line({"name": "openpi"}) == "openpi"
