"""What the MLflow UI shows of a run besides numbers: HTML reports and each cell's own slice.

MLflow's artifact viewer shows a Markdown file as text (its ``![..](figures/x.png)`` lines stay
literal) and an HTML file in a frame, so every report is also written as HTML with its figures
embedded as data URIs: one file that displays whole in the UI, in a browser, or mailed.

A child run (one cell) gets its own slice: the report restricted to the cell (the main table
with the reference it is paired with), its figures as PNG files, and its per-task rows, so
that a child run opened alone in the UI is readable without its parent.
"""

from __future__ import annotations

import base64
import html
import re
from pathlib import Path

from pipeline.reporting.figures import cell_figures, save
from pipeline.reporting.markdown import build_report
from pipeline.reporting.run_data import RunData
from pipeline.results import aggregate as agg
from pipeline.rundir import FIGURES_DIR, REPORT_MD

_IMG_SRC = re.compile(r'src="([^"]+\.png)"')
_STYLE = """
body { font-family: system-ui, sans-serif; margin: 1.5em; color: #1f2328; }
table { border-collapse: collapse; margin: 0.5em 0 1em; font-size: 0.9em; }
th, td { border: 1px solid #d0d7de; padding: 3px 8px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
th { background: #f6f8fa; }
img { max-width: 100%; }
code { background: #f6f8fa; padding: 0 3px; }
"""


def report_html(markdown_text: str, base: Path, title: str) -> str:
    """``markdown_text`` as a standalone HTML page; images it links (relative to ``base``)
    are embedded as data URIs, and one that is missing keeps its link."""
    from markdown_it import MarkdownIt

    body = MarkdownIt("commonmark").enable("table").render(markdown_text)

    def embed(m: re.Match[str]) -> str:
        path = base / html.unescape(m.group(1))
        if not path.is_file():
            return m.group(0)
        data = base64.b64encode(path.read_bytes()).decode("ascii")
        return f'src="data:image/png;base64,{data}"'

    body = _IMG_SRC.sub(embed, body)
    return (
        f'<!DOCTYPE html>\n<html><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{_STYLE}</style></head><body>\n{body}</body></html>\n"
    )


def write_report_html(report_md: Path, out_dir: Path | None = None) -> Path:
    """``report.html`` (next to ``report_md``, or in ``out_dir``), its figures embedded."""
    out = (out_dir or report_md.parent) / report_md.with_suffix(".html").name
    out.write_text(report_html(report_md.read_text(), report_md.parent, report_md.stem))
    return out


def write_cell_slice(run_dir: Path, data: RunData, cell: str, out: Path) -> list[Path]:
    """The cell's report.md and report.html, its figures and its per-task table into ``out``
    (what its child run shows as artifacts); returns the files written."""
    figs = cell_figures(data, cell)
    paths = {name: save(fig, out / FIGURES_DIR / f"{name}.png") for name, fig in figs.built.items()}
    text = build_report(run_dir, (paths, figs.skipped), focus=cell, episodes=data.episodes)
    md = out / REPORT_MD
    md.write_text(text)
    tables = out / "tables"
    tables.mkdir(parents=True, exist_ok=True)
    by_task = agg.success_by_task(data.episodes[data.episodes["cell_id"] == cell])
    agg.as_percent(by_task).to_csv(tables / "success_by_task.csv", index=False)
    return [md, write_report_html(md), *paths.values(), tables / "success_by_task.csv"]
