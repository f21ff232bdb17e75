"""``idr-eval ui`` and the Compare URL, client side: the URL, the store checks, the bind
address (the browser test is tests/pipeline/tracking/test_mlflow_ui_browser.py)."""

from __future__ import annotations

import json
import shutil
import sqlite3
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

import pytest

from pipeline import cli
from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import ConfigError, load_config
from pipeline.tracking.backend import check_store
from pipeline.tracking.ui import Selection, select

CONF = Path(__file__).resolve().parents[3] / "conf"


@pytest.fixture(scope="module")
def tracked(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ui")
    cfg = load_config(
        CONF / "smoke.yaml",
        [
            "executor.kind=inline",
            "episodes_per_task=1",
            "env.tasks=[reach]",
            f"tracking.uri=sqlite:///{out / 'mlflow.db'}",
        ],
    )
    execute(plan_run(cfg, out / "run"))
    return out / "run"


def test_compare_url_round_trips_the_run_ids() -> None:
    sel = Selection("sqlite:////x/mlflow.db", ["a1", "b2"], ["7"], ["r/baseline", "r/E"])
    url = sel.compare_url("http://127.0.0.1:5001/")
    parts = urlsplit(url)
    assert (parts.scheme, parts.netloc, parts.path) == ("http", "127.0.0.1:5001", "/")
    route, query = parts.fragment.split("?", 1)
    assert route == "/compare-runs"
    q = parse_qs(query)
    assert json.loads(q["runs"][0]) == ["a1", "b2"] and json.loads(q["experiments"][0]) == ["7"]
    assert q["workflowType"] == ["machine_learning"]
    assert " " not in url and '"' not in url  # one word in a terminal, clickable
    assert sel.search_filter == "attributes.run_id IN ('a1', 'b2')"


def test_selection_holds_only_cells_of_the_run(tracked) -> None:
    sel = select([tracked])
    state = json.loads((tracked / "tracking.json").read_text())
    assert sel.runs == list(state["children"].values())  # no parent run among them
    assert state["parent"] not in sel.runs and sel.experiments == [state["experiment_id"]]


def test_ui_refuses_a_run_dir_without_a_store(tracked, tmp_path, capsys) -> None:
    (tmp_path / "untracked" / "episodes").mkdir(parents=True)
    assert cli.main(["ui", str(tmp_path / "untracked")]) == 2
    assert "tracking.enabled=false" in capsys.readouterr().err
    copy = tmp_path / "copy"
    shutil.copytree(tracked, copy)  # its tracking.json names a store that is not there
    state = json.loads((copy / "tracking.json").read_text())
    state["uri"] = f"sqlite:///{tmp_path / 'gone' / 'mlflow.db'}"
    (copy / "tracking.json").write_text(json.dumps(state))
    assert cli.main(["ui", str(copy)]) == 2
    err = capsys.readouterr().err
    assert "does not exist" in err and "Traceback" not in err


def _with_revision(tracked: Path, tmp_path: Path, revision: str) -> str:
    db = tmp_path / f"{revision}.db"
    shutil.copy(tracked.parent / "mlflow.db", db)
    with sqlite3.connect(db) as c:
        c.execute("UPDATE alembic_version SET version_num = ?", (revision,))
    return f"sqlite:///{db}"


def test_a_store_of_another_mlflow_version_is_named(tracked, tmp_path) -> None:
    from pipeline.tracking.backend import _schema_revisions

    check_store(f"sqlite:///{tracked.parent / 'mlflow.db'}")  # this MLflow's: fine
    known, head = _schema_revisions()
    older = sorted(known - {head})[0]
    with pytest.raises(ConfigError, match=r"older MLflow .*`mlflow db upgrade"):
        check_store(_with_revision(tracked, tmp_path, older))
    with pytest.raises(ConfigError, match=r"newer MLflow"):
        check_store(_with_revision(tracked, tmp_path, "ffffffffffff"))


def test_ui_stays_on_localhost_and_says_so(tracked, monkeypatch, capsys) -> None:
    started = []

    class FakeServer:  # stands in for `mlflow ui`: records its command line
        def __init__(self, cmd, **_kw: object) -> None:
            started.append(cmd)

        def wait(self) -> int:
            return 0

        def poll(self) -> int:
            return 0

    monkeypatch.setattr("subprocess.Popen", FakeServer)
    assert cli.main(["ui", str(tracked), "--port", "5123"]) == 0
    out = capsys.readouterr().out
    cmd = started[0]
    assert cmd[cmd.index("--host") + 1] == "127.0.0.1" and cmd[cmd.index("--port") + 1] == "5123"
    assert "listens on 127.0.0.1 only" in out
    assert "side by side: http://127.0.0.1:5123/#/compare-runs?runs=" in out
    assert cli.main(["ui", str(tracked), "--host", "0.0.0.0"]) == 0
    captured = capsys.readouterr()
    assert "reachable from the network" in captured.err
