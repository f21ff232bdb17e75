"""A run's report files: RUN_DIR/report.md, report.html (its figures embedded) and figures/*.png.

The one place that composes the views: markdown and html are built here from the same run, and
a figure that fails never costs the run its report."""

from __future__ import annotations

import logging
from pathlib import Path

from pipeline.reporting.markdown import build_report
from pipeline.reporting.run_data import RunData
from pipeline.results.store import RunStore
from pipeline.rundir import REPORT_MD, write_text_atomic

log = logging.getLogger("idr_eval.report")


def write_report(run_dir: str | Path, figures: bool = True, data: RunData | None = None) -> Path:
    """Write RUN_DIR/report.md and report.html (and, with ``figures``, RUN_DIR/figures/*.png).
    ``data``: the run as the caller read it (the end of a run reads its store once and hands
    the same tables to the report, the figures and MLflow)."""
    run_dir = Path(run_dir)
    drawn: tuple[dict[str, Path], dict[str, str]] | str | None = None
    stored = (
        len(data.episodes) if data is not None else RunStore(run_dir, read_only=True).stored_count()
    )
    if figures and stored:
        try:
            from pipeline.reporting.figures import write_figures

            drawn = write_figures(run_dir, data)
        except Exception as e:  # a figure must never cost the run its report
            log.warning("figures failed: %s: %s", type(e).__name__, e, exc_info=True)
            drawn = f"{type(e).__name__}: {e}"
    text = build_report(run_dir, drawn, episodes=None if data is None else data.episodes)
    path = write_text_atomic(run_dir / REPORT_MD, text)
    try:  # report.html: the same, its figures embedded (what MLflow's artifact viewer shows)
        from pipeline.reporting.html import write_report_html

        write_report_html(path)
    except Exception as e:
        log.warning("report.html not written: %s: %s", type(e).__name__, e)
    return path
