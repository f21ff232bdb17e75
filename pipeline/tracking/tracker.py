"""MLflow tracking: one parent run per experiment run, one child run per IDR cell.

Only the driver talks to MLflow (SQLite locks under concurrent writers). By default the store
is SQLite next to the run directory (``<RUN_DIR>/../mlflow.db``), so all runs under one output
root share one store and can be compared side by side in the UI; ``tracking.uri`` selects any
other store (a tracking server for a cluster). Run ids are kept in ``RUN_DIR/tracking.json`` so
a resumed run logs into the same MLflow runs.

What the UI shows, and why:

- A child run carries only the parameters its cell's mode uses (``cell.alpha`` ... on refining
  cells; none of them on a baseline cell, the intervention settings on a diagnose cell), so a
  scatter or parallel-coordinates plot never places a cell at a value it ignores. The role
  (``idr.cell_role`` = baseline | diagnose | idr) and mode (``idr.mode``) are tags to filter on.
  The tau a cell used is the numeric param ``cell.tau_value`` (per suite
  ``cell.tau_value/<suite>`` when a run spans several); a calibrated tau's spelling stays in
  ``cell.tau``.
- Per-cell numbers live on the children (pipeline.tracking.metrics); R_img and the gate rate
  per progress bin are step-indexed metrics (``progress/r_img``; step = % of the episode), so
  MLflow's line charts overlay cells. Each child has its slice of the report (Markdown and HTML
  with its figures embedded), its figures and its per-task table as artifacts.
- The parent keeps run-level metrics only (episodes stored, errors, the calibrated tau) and the
  whole report (also as HTML), the figures, and the per-cell table ``tables/cells.csv``.
- The experiment is tagged as model development, so the UI opens in its ML view, not GenAI.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pandas as pd

from pipeline.results import aggregate as agg
from pipeline.rundir import FIGURES_DIR, TRACKING_FILE, VIDEOS_DIR, write_text_atomic
from pipeline.tracking.backend import answers, bounded_client, probe, sqlite_path, store_lock
from pipeline.tracking.metrics import (
    cell_metrics,
    cells_table,
    finite_only,
    metric_key,
    plain_value,
    rounded,
    task_tables,
)

if TYPE_CHECKING:
    from pipeline.reporting.run_data import RunData

log = logging.getLogger("idr_eval.tracking")
RECHECK_S = 2.0  # how often a tracking server that went down is asked whether it is back


#: The experiment tag MLflow's UI reads to choose its view (ML, not GenAI).
EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")
#: Metrics in percent (success and its differences): the unit of report.md and compare.
PERCENT_METRICS = ("success", "delta_")


def numerics_tags(episodes: pd.DataFrame) -> dict[str, dict[str, str]]:
    """Per cell, the numerical paths and hardware classes its episodes ran on, as MLflow tags
    (``idr.numerics``, ``idr.hardware``; several joined by " | ": a mixed cell). Cells of run dirs
    made before a column existed get no tag for it."""
    out: dict[str, dict[str, str]] = {}
    for cell_id, rows in episodes.groupby("cell_id"):
        tags = {}
        for column in ("numerics", "hardware"):
            if column in rows:
                values = sorted(str(v) for v in rows[column].dropna().unique())
                if values:
                    tags[f"idr.{column}"] = " | ".join(values)[:5000]
        out[str(cell_id)] = tags
    return out


class Tracker:
    """Parent + child MLflow runs of one RUN_DIR, created or resumed.

    A tracking server that goes down mid-run does not stop the run: what would be logged is
    held back (the episodes keep going to Parquet), sent when the server answers again, and at
    the end of a finished run the tracker waits up to ``reconnect_wait_s`` for it; if it is
    still down, it says so, and rerunning the same command (nothing is re-run) completes the
    MLflow runs. A server that is down at the start is refused before any work (:func:`probe`).
    A SQLite store that stops answering mid-run (a full disk, a damaged or vanished file) is
    held back the same way; a SQLite store is created and migrated under :func:`store_lock`, so
    drivers started at once on a new output root do not race on its schema.
    """

    def __init__(
        self, uri: str, experiment: str, run_dir: Path, reconnect_wait_s: float = 60.0
    ) -> None:
        probe(uri)
        self.uri = uri
        self.run_dir = run_dir
        self.reconnect_wait_s = reconnect_wait_s
        self._server = uri.startswith(("http://", "https://"))
        self._pending: list[Callable[[], None]] = []  # held back while the server is down
        self._down_since: float | None = None
        self._next_probe = 0.0
        self.offline_seconds = 0.0  # how long the server was down during this run
        path = sqlite_path(uri)
        try:
            # MLflow creates (and migrates) a SQLite store when its client is made
            with store_lock(path) if path else contextlib.nullcontext():
                # short retries: a server that went down is noticed by probe(), caught up later
                self.client = bounded_client(uri)
                self.experiment_id = self._experiment(experiment)
        except Exception as e:
            raise RuntimeError(
                f"MLflow store {uri} is not usable: {type(e).__name__}: {e}"
            ) from None
        self.parent_id: str | None = None
        self.children: dict[str, str] = {}
        self._uses_tau: set[str] = set()
        self._done = 0

    def _experiment(self, name: str) -> str:
        """The experiment's id, created if new (the store's schema with it, on first use)."""
        exp = self.client.get_experiment_by_name(name)
        if exp is None:
            try:
                exp_id = self.client.create_experiment(
                    name, artifact_location=self._artifact_location()
                )
            except Exception:  # created meanwhile by a driver on another store lock (a server)
                exp = self.client.get_experiment_by_name(name)
                if exp is None:
                    raise
                exp_id = exp.experiment_id
        else:
            exp_id = exp.experiment_id
        if exp is None or EXPERIMENT_KIND[0] not in exp.tags:  # a user's choice stands
            self.client.set_experiment_tag(exp_id, *EXPERIMENT_KIND)
        return exp_id

    def _artifact_location(self) -> str | None:
        if self.uri.startswith("sqlite:///"):
            return (Path(self.uri.removeprefix("sqlite:///")).parent / "mlartifacts").as_uri()
        return None

    def start(
        self, *, run_name: str, run_id: str, params: dict[str, Any], cells: list[Any]
    ) -> None:
        path = self.run_dir / TRACKING_FILE
        state = json.loads(path.read_text()) if path.is_file() else {}
        if state.get("uri") == self.uri and state.get("parent"):
            self.parent_id = state["parent"]
            self.children = dict(state.get("children", {}))
            self.client.update_run(self.parent_id, status="RUNNING")
        else:
            tags = {
                "idr.run_id": run_id,
                "idr.run_dir": str(self.run_dir.resolve()),
                "idr.role": "run",
                **{f"idr.{k}": str(params[k]) for k in ("backbone", "suite") if k in params},
            }
            self.parent_id = self.client.create_run(
                self.experiment_id, run_name=run_name, tags=tags
            ).info.run_id
            self._log_params(self.parent_id, params)
        self._uses_tau = {c.cell_id for c in cells if "tau" in c.meaningful_params()}
        for cell in cells:
            if cell.cell_id in self.children:
                self.client.update_run(self.children[cell.cell_id], status="RUNNING")
                continue
            meaningful = cell.meaningful_params()
            tags = {
                "mlflow.parentRunId": self.parent_id,
                "idr.run_id": run_id,
                "idr.cell": cell.cell_id,
                "idr.role": "cell",
                "idr.cell_role": cell.role,
                "idr.run_name": run_name,
                "idr.run_dir": str(self.run_dir.resolve()),
                "idr.varied": ", ".join(f"{k}={plain_value(v)}" for k, v in cell.varied),
                **{f"idr.{k}": str(params[k]) for k in ("backbone", "suite") if k in params},
                **{f"idr.{k}": str(v) for k, v in meaningful.items()},
            }
            child = self.client.create_run(
                self.experiment_id, run_name=f"{run_name}/{cell.cell_id}", tags=tags
            )
            self.children[cell.cell_id] = child.info.run_id
            cell_params = {f"cell.{k}": v for k, v in meaningful.items()}
            if "tau" in meaningful and cell.calibrated_tau is None:
                cell_params["cell.tau_value"] = cell.idr.tau  # calibrated: logged once measured
            self._log_params(child.info.run_id, {**params, **cell_params})
        write_text_atomic(
            path,
            json.dumps(
                {
                    "uri": self.uri,
                    "experiment_id": self.experiment_id,
                    "parent": self.parent_id,
                    "children": self.children,
                },
                indent=2,
            ),
        )

    def _log_params(self, run_id: str, params: dict[str, Any]) -> None:
        from mlflow.entities import Param

        items = [Param(k, str(v)[:6000]) for k, v in params.items()]
        for i in range(0, len(items), 100):
            self.client.log_batch(run_id, params=items[i : i + 100])

    def _log_metrics(self, run_id: str, metrics: dict[str, float], step: int = 0) -> None:
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(k, v, now, step) for k, v in finite_only(metrics).items()]
        for i in range(0, len(items), 500):
            self.client.log_batch(run_id, metrics=items[i : i + 500])

    def _log_series(self, run_id: str, series: dict[str, list[tuple[int, float]]]) -> None:
        """Step-indexed metrics ``progress/<name>`` in one batch."""
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [
            Metric(metric_key("progress", name), rounded(v), now, step)
            for name, points in series.items()
            for step, v in points
            if math.isfinite(v)
        ]
        for i in range(0, len(items), 500):
            self.client.log_batch(run_id, metrics=items[i : i + 500])

    def log_calibration(self, result: dict[str, Any]) -> None:
        """The calibrated tau on the parent and on every child that uses it."""
        self._call(lambda: self._log_calibration(result))

    def _log_calibration(self, result: dict[str, Any]) -> None:
        self._log_params(
            self.parent_id, {"tau_calibrated": result["tau"], "tau_source": result["source_cell"]}
        )
        self._log_metrics(self.parent_id, {"tau_calibrated": float(result["tau"])})
        held_out = result.get("fitted_on") == "held_out"
        self._log_params(self.parent_id, {"tau_fitted_on": result.get("fitted_on", "evaluated")})
        for g in result.get("groups", []):  # the statistic, on the diagnose cell it measured
            if held_out:  # held-out episodes: in no metric of the evaluated cells
                key = metric_key("heldout_e_img_mean", g["source_cell"], g["suite"])
                self._log_metrics(self.parent_id, {key: g["e_img_mean"]})
                continue
            rid = self.children.get(g["source_cell"])
            if rid is not None:
                self._log_metrics(rid, {metric_key("e_img_mean", g["suite"]): g["e_img_mean"]})
        for cell_id, c in result.get("cells", {}).items():
            rid = self.children.get(cell_id)
            if rid is None:
                continue
            metrics = {metric_key("tau", suite): tau for suite, tau in c["tau"].items()}
            params = {metric_key("cell.tau_value", s): rounded(t) for s, t in c["tau"].items()}
            if len(c["tau"]) == 1:
                metrics["tau"] = next(iter(c["tau"].values()))
                params = {"cell.tau_value": rounded(metrics["tau"])}
            self._log_metrics(rid, metrics)
            if cell_id in self._uses_tau:  # mode D has no gate: no tau to plot it at
                self._log_params(rid, params)
            value = ", ".join(f"{suite}={tau:.4g}" for suite, tau in c["tau"].items())
            self.client.set_tag(rid, "idr.tau_value", value)

    # -- a tracking server that goes down mid-run --------------------------------------------
    @property
    def online(self) -> bool:
        """False while the tracking server is down (asked again at most every RECHECK_S)."""
        if self._down_since is None:
            return True
        now = time.monotonic()
        if now < self._next_probe:
            return False
        self._next_probe = now + RECHECK_S
        if not answers(self.uri):
            return False
        down = now - self._down_since
        self.offline_seconds += down
        self._down_since = None
        log.warning(
            "MLflow tracking server %s answers again after %.0f s down: sending the %d "
            "update(s) held back",
            self.uri,
            down,
            len(self._pending),
        )
        return True

    def _went_down(self, exc: BaseException) -> None:
        self._next_probe = time.monotonic() + RECHECK_S
        if self._down_since is None:
            self._down_since = time.monotonic()
            log.warning(
                "MLflow tracking server %s is down (%s: %s): the run goes on and the episodes "
                "keep going to Parquet; MLflow is updated when the server is back, or at the end",
                self.uri,
                type(exc).__name__,
                str(exc).splitlines()[0][:200] if str(exc) else "",
            )

    def _flush_pending(self) -> bool:
        """Send what was held back; False (and kept) while the server is down."""
        if not self.online:
            return False
        while self._pending:
            try:
                self._pending[0]()
            except Exception as exc:
                if answers(self.uri):
                    raise  # the store answers: not an outage but a real error
                self._went_down(exc)
                return False
            self._pending.pop(0)
        return True

    def _call(self, fn: Callable[[], None]) -> bool:
        self._pending.append(fn)
        return self._flush_pending()

    def progress(self, n_new: int, total: int) -> None:
        self._done += n_new
        if self.parent_id:
            parent, done = self.parent_id, self._done
            self._call(lambda: self._log_metrics(parent, {"episodes_stored": done}, step=done))

    def finish(
        self,
        episodes: pd.DataFrame,
        artifacts: list[Path],
        status: str = "FINISHED",
        data: RunData | None = None,
    ) -> bool:
        """Log the per-cell metrics and the artifacts, and end the runs with ``status``;
        ``data``: the run as the caller read it (else read here for the cells' slices).

        Returns False when the tracking server is down and stayed down (for up to
        ``reconnect_wait_s`` after a finished run): MLflow is then left to a rerun."""
        if self._call(lambda: self._finish(episodes, artifacts, status, data)):
            return True
        wait = self.reconnect_wait_s if status == "FINISHED" else 0.0
        if wait > 0:
            log.warning(
                "waiting up to %g s for the MLflow tracking server %s to come back", wait, self.uri
            )
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            time.sleep(min(RECHECK_S, max(deadline - time.monotonic(), 0.0)))
            self._next_probe = 0.0
            if self._flush_pending():
                return True
        log.error(
            "MLflow was not updated: the tracking server %s is down. The results are complete "
            "in %s; run the same `idr-eval run` command again once the server is back: nothing "
            "is re-run, and the MLflow runs get their metrics and artifacts and end as %s",
            self.uri,
            self.run_dir,
            status,
        )
        return False

    def _finish(
        self, episodes: pd.DataFrame, artifacts: list[Path], status: str, data: RunData | None
    ) -> None:
        if not episodes.empty:
            chains = agg.chain_metrics(episodes)  # bootstrapped once, for both below
            per_cell = cell_metrics(episodes, chains)
            with tempfile.TemporaryDirectory() as tmp:
                paths = task_tables(episodes, Path(tmp), chains)
                paths.append(Path(tmp) / "cells.csv")
                cells_table(per_cell).to_csv(paths[-1], index=False)
                for path in paths:
                    self.client.log_artifact(self.parent_id, str(path), "tables")
            for cell_id, metrics in per_cell.items():
                if cell_id in self.children:
                    self._log_metrics(self.children[cell_id], metrics)
            for cell_id, tags in numerics_tags(episodes).items():
                for key, value in tags.items():
                    if cell_id in self.children:
                        self.client.set_tag(self.children[cell_id], key, value)
            self._log_metrics(
                self.parent_id,
                {
                    "episodes": len(episodes),
                    "errors": int(episodes["error"].notna().sum()),
                    "cells": int(episodes["cell_id"].nunique()),
                },
            )
            self._log_cell_views(data)
        self._log_videos()
        for p in artifacts:
            if p.exists():
                folder = FIGURES_DIR if p.suffix == ".png" else None
                self.client.log_artifact(self.parent_id, str(p), folder)
        for rid in self.children.values():
            self.client.set_terminated(rid, status=status)
        self.client.set_terminated(self.parent_id, status=status)

    def _log_videos(self) -> None:
        """Each cell's episode videos (RUN_DIR/videos/cell=<id>/, videos.episodes) under
        ``videos/`` of its child run."""
        for cell_id, rid in self.children.items():
            folder = self.run_dir / VIDEOS_DIR / f"cell={cell_id}"
            if folder.is_dir() and any(folder.rglob("*.mp4")):
                self.client.log_artifacts(rid, str(folder), VIDEOS_DIR)

    def _log_cell_views(self, data: RunData | None = None) -> None:
        """Each child's slice of the report (and its figures, its per-task table) as artifacts,
        and its progress curves as step-indexed metrics. A failure here (a figure) is logged
        and never costs the run its metrics or its status."""
        from pipeline.reporting.figures import progress_curves
        from pipeline.reporting.html import write_cell_slice
        from pipeline.reporting.run_data import load_run

        try:
            data = data if data is not None else load_run(self.run_dir)
            curves = progress_curves(data)
            for cell_id, rid in self.children.items():
                if not (data.episodes["cell_id"] == cell_id).any():
                    continue
                with tempfile.TemporaryDirectory() as tmp:
                    write_cell_slice(self.run_dir, data, cell_id, Path(tmp))
                    self.client.log_artifacts(rid, tmp)
                self._log_series(rid, curves.get(cell_id, {}))
        except Exception as e:
            log.warning(
                "the cells' report slices for MLflow failed: %s: %s",
                type(e).__name__,
                e,
                exc_info=True,
            )
