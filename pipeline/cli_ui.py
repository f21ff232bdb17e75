"""``idr-eval ui``: the MLflow UI for run dirs' store, at their cells' Compare page."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path


def _cmd_ui(args: argparse.Namespace) -> int:
    """Start the MLflow UI for the run dirs' store (127.0.0.1 unless --host says otherwise),
    printing the Compare URL of their cells (``--open``: opened in a browser)."""
    import subprocess

    from pipeline.tracking.backend import check_store, default_uri
    from pipeline.tracking.ui import LOCAL_HOSTS, remote_ui_help, select, ui_base

    sel = None
    if args.run_dirs:
        sel = select([Path(p) for p in args.run_dirs])
        uri = sel.uri
    else:
        uri = default_uri(Path("runs") / "_")
    if not uri.startswith("sqlite:"):
        print(remote_ui_help(uri))
        if sel is not None:
            print(f"the cells side by side: {sel.compare_url(ui_base(uri))}")
        return 0
    check_store(uri)
    base = ui_base(uri, args.host, args.port)
    cmd = [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", uri]
    cmd += ["--host", args.host, "--port", str(args.port), "--workers", str(args.workers)]
    print(f"MLflow UI for {uri} on {base} (Ctrl-C to stop)")
    if args.host in LOCAL_HOSTS:
        print(
            f"it listens on {args.host} only: this machine; from another one, tunnel "
            f"(ssh -N -L {args.port}:127.0.0.1:{args.port} USER@THIS_HOST) or pass --host 0.0.0.0"
        )
    else:
        print(
            f"idr-eval: warning: --host {args.host} makes the MLflow UI (no authentication) "
            "reachable from the network; prefer 127.0.0.1 and an SSH tunnel",
            file=sys.stderr,
        )
    url = sel.compare_url(base) if sel is not None and sel.runs else base
    if sel is not None and sel.runs:
        print(f"the {len(sel.runs)} cells side by side: {url}")
    # the job runner MLflow starts beside its UI serves GenAI jobs: not needed here
    env = {"MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false", **os.environ}
    proc = subprocess.Popen(cmd, env=env)
    if args.open:
        _open_when_up(base, url, proc)
    try:
        return proc.wait()
    except KeyboardInterrupt:
        proc.terminate()
        return proc.wait()


def _open_when_up(base: str, url: str, proc: object) -> None:
    """Open ``url`` in the user's browser once the UI answers (up to 60 s)."""
    import time
    import urllib.request
    import webbrowser

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:  # type: ignore[attr-defined]
        try:
            with urllib.request.urlopen(f"{base}/health", timeout=2):
                break
        except OSError:
            time.sleep(0.5)
    if not webbrowser.open(url):
        print(f"no browser to open here: open {url}")


def add_ui(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    ui = sub.add_parser(
        "ui",
        help="MLflow UI for run dirs' store (default: runs/mlflow.db), at their cells' Compare page",
    )
    ui.add_argument("run_dirs", nargs="*", metavar="RUN_DIR")
    ui.add_argument("--open", action="store_true", help="open the Compare page in a browser")
    ui.add_argument(
        "--host", default="127.0.0.1", help="bind address (default 127.0.0.1: local only)"
    )
    ui.add_argument("--port", type=int, default=5000)
    ui.add_argument(
        "--workers", type=int, default=1, help="server processes (MLflow's default 4; one user: 1)"
    )
    ui.set_defaults(func=_cmd_ui)
