"""The evaluator's record of a training run: ``RUN/evals/evals.jsonl`` (the steps evaluated,
what ran, figures or errors; the resume record) and the one MLflow run per member x seed that
holds the figures as metrics against the training step (``training.zoo_evaluator``)."""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

from training.zoo_eval_layout import CURRENT, EXPERIMENT, LEDGER, RUN_ID_FILE, log

if TYPE_CHECKING:
    pass


# --- the record ------------------------------------------------------------------------------


class Ledger:
    """``RUN/evals/evals.jsonl`` (one line per evaluated step, appended and flushed) and the
    marker of the step under evaluation."""

    def __init__(self, evals: Path) -> None:
        self.evals = evals
        self.path = evals / LEDGER
        self.current = evals / CURRENT

    def records(self) -> list[dict[str, Any]]:
        if not self.path.is_file():
            return []
        out = []
        for line in self.path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:  # a line cut by a crash mid-write
                continue
        return out

    def done(self) -> set[int]:
        """Steps evaluated (or failed) already: never again. A checkpoint recorded incomplete is
        tried again once it is whole (a resumed training may save that step again)."""
        return {r["step"] for r in self.records() if r.get("status") in ("ok", "error")}

    def append(self, record: dict[str, Any]) -> None:
        self.evals.mkdir(parents=True, exist_ok=True)
        with self.path.open("a") as f:
            f.write(json.dumps(record, default=float) + "\n")
            f.flush()
            os.fsync(f.fileno())

    def begin(self, step: int) -> None:
        self.evals.mkdir(parents=True, exist_ok=True)
        self.current.write_text(json.dumps({"step": step, "pid": os.getpid(), "t": time.time()}))

    def end(self) -> None:
        self.current.unlink(missing_ok=True)

    def interrupted_step(self) -> int | None:
        """The step a killed evaluator was evaluating (its marker is still there), if any."""
        if not self.current.is_file():
            return None
        try:
            step = int(json.loads(self.current.read_text())["step"])
        except (ValueError, KeyError, json.JSONDecodeError):
            return None
        return None if step in self.done() else step


# --- MLflow ----------------------------------------------------------------------------------


class TrainingRun:
    """The member x seed's MLflow run in experiment ``zoo-training``: params once, metrics per
    evaluated step, an ``error_step_<step>`` tag per failure. Its id is kept in
    ``RUN/evals/mlflow_run_id``, so a restarted evaluator logs into the same run. A store that
    fails mid-way is reported on the evaluator's log and never stops an evaluation
    (evals.jsonl is the record)."""

    def __init__(self, uri: str, evals: Path, name: str) -> None:
        from pipeline.rundir import write_text_atomic
        from pipeline.tracking.tracker import Tracker

        # the store created under its lock, the experiment with its UI kind, as a run's are
        tracker = Tracker(uri, EXPERIMENT, evals)
        self.client = tracker.client
        self.uri = uri
        id_file = evals / RUN_ID_FILE
        run_id = id_file.read_text().strip() if id_file.is_file() else ""
        if run_id and self._exists(run_id):
            self.client.update_run(run_id, status="RUNNING")
        else:  # new, or the id of another store (the URI changed)
            tags = {"idr.role": "training", "idr.run_dir": str(evals.parent.resolve())}
            run_id = self.client.create_run(
                tracker.experiment_id, run_name=name, tags=tags
            ).info.run_id
            evals.mkdir(parents=True, exist_ok=True)
            write_text_atomic(id_file, run_id + "\n")
        self.run_id = run_id

    def _exists(self, run_id: str) -> bool:
        try:
            self.client.get_run(run_id)
        except Exception:
            return False
        return True

    def params(self, params: dict[str, Any]) -> None:
        """Log params not logged yet; one that differs from a past session's becomes a tag
        ``param_changed.<name>`` (MLflow keeps a param's first value)."""
        self._safe(lambda: self._params(params))

    def _params(self, params: dict[str, Any]) -> None:
        from mlflow.entities import Param

        have = self.client.get_run(self.run_id).data.params
        new = [Param(k, str(v)[:6000]) for k, v in params.items() if k not in have]
        if new:
            self.client.log_batch(self.run_id, params=new)
        for k, v in params.items():
            if k in have and have[k] != str(v)[:6000]:
                log(f"param {k} was {have[k]!r}, is now {v!r} (tagged param_changed.{k})")
                self.client.set_tag(self.run_id, f"param_changed.{k}", str(v)[:5000])

    def metrics(self, step: int, metrics: dict[str, float]) -> None:
        self._safe(lambda: self._metrics(step, metrics))

    def _metrics(self, step: int, metrics: dict[str, float]) -> None:
        from mlflow.entities import Metric

        from pipeline.tracking.metrics import finite_only

        now = int(time.time() * 1000)
        items = [Metric(k, v, now, step) for k, v in finite_only(metrics).items()]
        if items:
            self.client.log_batch(self.run_id, metrics=items)

    def error(self, step: int, message: str) -> None:
        self._safe(lambda: self.client.set_tag(self.run_id, f"error_step_{step}", message[:5000]))

    def close(self, status: str) -> None:
        self._safe(lambda: self.client.set_terminated(self.run_id, status=status))

    def _safe(self, fn: Callable[[], Any]) -> None:
        try:
            fn()
        except Exception as e:
            log(f"MLflow store {self.uri}: {type(e).__name__}: {e} (evals.jsonl has the figures)")
