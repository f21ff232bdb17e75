"""The MLflow UI over run dirs: which store they log to, the cells' Compare URL, and a UI to
open it (``idr-eval ui RUN_DIR...``).

MLflow's Compare page takes its runs from the URL (``#/compare-runs?runs=[ids]&experiments=
[ids]``); its search box has no OR over tags, so a list of run ids is how several runs of
several run dirs are selected. The URL opens the comparison of exactly the cells given, with
no parent run among them (a parent in a selection drags its children along in the UI).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

from pipeline.planning.config import ConfigError
from pipeline.reporting.compare import RunEpisodes
from pipeline.rundir import TRACKING_FILE

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
    from pipeline.tracking.backend import answers, bounded_client

    if uri.startswith(("http://", "https://")) and not answers(uri):
        return []  # a server out of reach: the URL without its experiments still opens
    client = bounded_client(uri)
    try:
        return list(dict.fromkeys(client.get_run(r).info.experiment_id for r in run_ids))
    except Exception:  # a store out of reach: the URL without its experiments still opens
        return []


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


def mlflow_lines(runs: list[RunEpisodes], ui: str | None = None) -> list[str]:
    """How to see the compared cells in the MLflow UI: the Compare page's URL (of ``idr-eval
    ui``'s address, or the tracking server's) and the runs-table filter; or why there is none."""
    dirs = [r.run_dir for r in runs if r.run_dir is not None]
    try:
        sel = select(dirs, {r.run_dir: set(r.episodes["cell_id"]) for r in runs if r.run_dir})
    except ConfigError as e:
        return [f"No MLflow selection: {e}."]
    base = ui or ui_base(sel.uri)
    start = (
        ""
        if sel.uri.startswith(("http://", "https://"))
        else f" (start it with `idr-eval ui {' '.join(str(d) for d in dirs)}`)"
    )
    return [
        f"MLflow ({sel.uri}): the {len(sel.runs)} cells side by side in the UI{start}:",
        "",
        f"    {sel.compare_url(base)}",
        "",
        "or paste this into the runs table's search box:",
        "",
        f"    {sel.search_filter}",
    ]
