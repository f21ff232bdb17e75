"""The MLflow UI over run dirs: which store they log to, the cells' Compare URL, and a UI to
open it (``idr-eval ui RUN_DIR...``).

MLflow's Compare page takes its runs from the URL (``#/compare-runs?runs=[ids]&experiments=
[ids]``); its search box has no OR over tags, so a list of run ids is how several runs of
several run dirs are selected. The URL opens the comparison of exactly the cells given, with
no parent run among them (a parent in a selection drags its children along in the UI).
"""

from __future__ import annotations

import json
import sqlite3
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

from pipeline.config import ConfigError
from pipeline.tracking import TRACKING_FILE

LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1")
DEFAULT_UI = "http://127.0.0.1:5000"


@dataclass
class Selection:
    """The child runs (cells) of some run dirs in one MLflow store."""

    uri: str
    runs: list[str] = field(default_factory=list)  # MLflow run ids, in the run dirs' order
    experiments: list[str] = field(default_factory=list)
    cells: list[str] = field(default_factory=list)  # "<run dir name>/<cell>", as runs

    @property
    def search_filter(self) -> str:
        """The runs-table search that selects the same runs."""
        return "attributes.run_id IN (" + ", ".join(f"'{i}'" for i in self.runs) + ")"

    def compare_url(self, base: str = DEFAULT_UI) -> str:
        """MLflow's Compare page of the cells (JSON lists, percent-encoded for terminals)."""
        runs = quote(json.dumps(self.runs, separators=(",", ":")), safe="")
        exps = quote(json.dumps(self.experiments, separators=(",", ":")), safe="")
        return (
            f"{base.rstrip('/')}/#/compare-runs?runs={runs}&experiments={exps}"
            "&workflowType=machine_learning"  # the UI's model-training view, not GenAI
        )


def tracking_state(run_dir: Path) -> dict:
    """RUN_DIR/tracking.json, or ConfigError saying the run dir was not tracked."""
    path = run_dir / TRACKING_FILE
    if not path.is_file():
        raise ConfigError(
            f"{run_dir} has no MLflow runs ({TRACKING_FILE} is missing): it was run with "
            "tracking.enabled=false, or is not a run dir; run it with tracking.enabled=true"
        )
    return json.loads(path.read_text())


def select(run_dirs: list[Path], cells: dict[Path, set[str]] | None = None) -> Selection:
    """The cells of ``run_dirs`` (of ``cells[run_dir]`` where given) as one selection;
    ConfigError when a run dir was not tracked or the run dirs log to different stores."""
    states = {p: tracking_state(p) for p in run_dirs}
    uris = {s["uri"] for s in states.values()}
    if len(uris) != 1:
        shown = ", ".join(f"{p} -> {s['uri']}" for p, s in states.items())
        raise ConfigError(
            f"the run dirs log to different MLflow stores ({shown}); one UI shows one store: "
            "compare run dirs of one output root (or one tracking.uri)"
        )
    sel = Selection(uris.pop())
    missing: list[str] = []
    for p, state in states.items():
        wanted = cells.get(p) if cells else None
        for cell, rid in state.get("children", {}).items():
            if wanted is None or cell in wanted:
                sel.runs.append(rid)
                sel.cells.append(f"{p.name}/{cell}")
        exp = state.get("experiment_id")
        if exp is None:
            missing.append(state["parent"])
        elif exp not in sel.experiments:
            sel.experiments.append(exp)
    for exp in _experiments_of(sel.uri, missing):  # run dirs tracked before ids were kept
        if exp not in sel.experiments:
            sel.experiments.append(exp)
    return sel


def _experiments_of(uri: str, run_ids: list[str]) -> list[str]:
    if not run_ids:
        return []
    from pipeline.tracking import answers, bounded_client

    if uri.startswith(("http://", "https://")) and not answers(uri):
        return []  # a server out of reach: the URL without its experiments still opens
    client = bounded_client(uri)
    try:
        return list(dict.fromkeys(client.get_run(r).info.experiment_id for r in run_ids))
    except Exception:  # a store out of reach: the URL without its experiments still opens
        return []


def check_store(uri: str, damaged_hint: bool = False) -> None:
    """Refuse, before a UI or a run starts, a SQLite store that is not there, is damaged, is
    not an MLflow store, or that another version of MLflow wrote (its UI would fail on it, or
    offer to migrate it). ``damaged_hint``: the refusal says how a run can go on without it."""
    if not uri.startswith("sqlite:///"):
        return
    path = Path(uri.removeprefix("sqlite:///"))
    if not path.is_file():
        raise ConfigError(
            f"the MLflow store {path} does not exist: run a config with tracking enabled first "
            "(its runs go to <output_root>/mlflow.db), or name a run dir that was tracked"
        )
    aside = (
        f"; move it aside (mv {path} {path}.bad) to start a new store, or set "
        "tracking.enabled=false to run without MLflow"
        if damaged_hint
        else ""
    )
    try:
        with sqlite3.connect(f"file:{path}?mode=ro", uri=True) as db:
            ok = db.execute("PRAGMA quick_check(1)").fetchone()
            if ok is None or ok[0] != "ok":
                raise sqlite3.DatabaseError(f"quick_check: {ok[0] if ok else 'no answer'}")
            row = db.execute("SELECT version_num FROM alembic_version").fetchone()
    except sqlite3.DatabaseError as e:
        raise ConfigError(f"{path} is not a readable MLflow store ({e}){aside}") from None
    found = row[0] if row else None
    known, head = _schema_revisions()
    if found == head:
        return
    import mlflow

    if found in known:
        raise ConfigError(
            f"{path} was written by an older MLflow (schema {found}; this MLflow "
            f"{mlflow.__version__} expects {head}): back it up, then upgrade it with "
            f"`mlflow db upgrade {uri}`, or open it with the MLflow version that wrote it"
        )
    raise ConfigError(
        f"{path} was written by a newer MLflow than this one ({mlflow.__version__}; unknown "
        f"schema {found}): open it with that MLflow's UI (`mlflow ui --backend-store-uri {uri}`)"
    )


def _schema_revisions() -> tuple[set[str], str]:
    """The store schema revisions this MLflow knows, and its head (alembic's script dir)."""
    import mlflow
    from alembic.script import ScriptDirectory

    scripts = ScriptDirectory(str(Path(mlflow.__file__).parent / "store" / "db_migrations"))
    return {s.revision for s in scripts.walk_revisions()}, str(scripts.get_current_head())


def remote_ui_help(uri: str) -> str:
    """How to open the UI of a tracking server (it serves its own UI; nothing to start here)."""
    from urllib.parse import urlsplit

    parts = urlsplit(uri)
    host, port = parts.hostname or "SERVER", parts.port or (443 if parts.scheme == "https" else 80)
    if host in LOCAL_HOSTS:
        return f"{uri} is a tracking server on this machine: open {uri} in a browser."
    return (
        f"{uri} is a tracking server: it serves its own UI, nothing to start here. Open {uri} in "
        "a browser if it is reachable from here; otherwise (it listens on a cluster's private "
        f"network) tunnel to it and open http://127.0.0.1:{port}:\n"
        f"  ssh -N -L {port}:{host}:{port} USER@HEAD_NODE        # a VM cluster (ray up)\n"
        f"  kubectl port-forward svc/{host.split('.')[0]} {port}:{port}   # Kubernetes (KubeRay)"
    )


def ui_base(uri: str, host: str = "127.0.0.1", port: int = 5000) -> str:
    """Where the UI of ``uri`` is served: a tracking server's own address, else
    ``idr-eval ui``'s."""
    if uri.startswith(("http://", "https://")):
        return uri.rstrip("/")
    shown = "127.0.0.1" if host in ("0.0.0.0", "::") else host
    return f"http://{shown}:{port}"
