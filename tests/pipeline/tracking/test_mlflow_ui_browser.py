"""The MLflow UI in a real browser: Debian's chromium, driven headless by Playwright (the system
executable; no browser is downloaded), against ``idr-eval ui`` (a real ``mlflow ui`` on
127.0.0.1) over a small real run of the tabletop with the shipped tiny VLA.

It opens the Compare URL that ``idr-eval ui`` prints and checks the page lists the run's cells,
each with its mode and its success in percent, as MLflow's client reads them. With
``IDR_SCREENSHOT=PATH`` it saves the page there (the README's screenshot is made so).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from pipeline.execution.runner import execute, plan_run
from pipeline.planning.config import load_config

ROOT = Path(__file__).resolve().parents[3]
CHROMIUM = shutil.which("chromium")
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        CHROMIUM is None, reason="Debian's chromium is not installed (apt-get install chromium)"
    ),
]

# a metric's values on the Compare page: its names and values are two virtualized grids (only
# the rows in view exist), rows placed by their CSS top; scrolled until the row is rendered
METRIC_JS = """async key => {
  const grids = [...document.querySelectorAll('.ReactVirtualized__Grid')];
  const find = () => [...document.querySelectorAll('a[title="Plot chart"]')]
    .find(a => a.textContent.trim() === key);
  const sleep = ms => new Promise(r => setTimeout(r, ms));
  let link = find();
  for (let y = 0; !link && grids.length && y < grids[0].scrollHeight; y += 150) {
    for (const g of grids) { g.scrollTop = y; g.dispatchEvent(new Event('scroll')); }
    await sleep(100);
    link = find();
  }
  if (!link) return null;
  const top = link.parentElement.style.top;
  for (const g of grids) {
    g.scrollTop = Math.max(parseInt(top) - 100, 0);
    g.dispatchEvent(new Event('scroll'));
  }
  await sleep(300);
  for (const g of grids) {
    const cells = [...g.querySelectorAll(':scope > div > div')].filter(d => d.style.top === top);
    if (cells.length)
      return cells.sort((a, b) => parseInt(a.style.left) - parseInt(b.style.left))
        .map(d => d.textContent.trim());
  }
  return null;
}"""

# one row of MLflow's compare tables: <tr><th scope=row>KEY</th><td>run 1</td><td>run 2</td>...
ROW_JS = """key => {
  for (const tr of document.querySelectorAll('tr')) {
    const th = tr.querySelector('th');
    if (th && th.innerText.trim() === key)
      return Array.from(tr.querySelectorAll('td')).map(td => td.innerText.trim());
  }
  return null;
}"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_up(base: str, proc: subprocess.Popen, timeout: float = 120.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise AssertionError(f"idr-eval ui exited with {proc.returncode}")
        try:
            with urllib.request.urlopen(f"{base}/health", timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            time.sleep(0.5)
    raise AssertionError(f"the MLflow UI at {base} did not answer within {timeout:g} s")


@pytest.fixture(scope="module")
def tracked_run(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ui")
    cfg = load_config(
        ROOT / "conf" / "default.yaml",
        [
            "env.tasks=[pick_color]",
            "episodes_per_task=3",
            "executor.kind=inline",
            f"tracking.uri=sqlite:///{out / 'mlflow.db'}",
        ],
    )
    execute(plan_run(cfg, out / "default"))
    return out / "default"


def test_the_printed_compare_url_shows_the_cells_with_mode_and_success(tracked_run) -> None:
    from mlflow import MlflowClient
    from playwright.sync_api import sync_playwright

    from pipeline.tracking.ui import tracking_state

    state = tracking_state(tracked_run)
    client = MlflowClient(state["uri"])
    expected = {}  # run name -> (mode, success as the UI writes it)
    for cell, rid in state["children"].items():
        run = client.get_run(rid)
        expected[run.info.run_name] = (cell, f"{run.data.metrics['success']:g}")
    port = _free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "pipeline.cli", "ui", str(tracked_run), "--port", str(port)],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,  # mlflow ui starts uvicorn and a job runner: one group to stop
    )
    try:
        url = None
        for line in proc.stdout:  # type: ignore[union-attr]
            if "side by side:" in line:
                url = line.split("side by side:", 1)[1].strip()
                break
        assert url and url.startswith(f"http://127.0.0.1:{port}/#/compare-runs?runs=")
        _wait_up(f"http://127.0.0.1:{port}", proc)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1400, "height": 1000})
            page.goto(url)
            page.wait_for_selector("text=Comparing 2 Runs from 1 Experiment", timeout=90_000)
            page.wait_for_function("() => document.querySelectorAll('th').length > 20")
            if shot := os.environ.get(
                "IDR_SCREENSHOT"
            ):  # the README's: tall, plot drawn; taken before
                # METRIC_JS scrolls the metric grids out of step
                page.set_viewport_size({"width": 1400, "height": 2000})
                close = page.locator(
                    "button[data-component-id='mlflow.assistant.chat_panel.close']"
                )
                if close.count():  # MLflow's assistant panel, open by default
                    close.click()
                page.wait_for_selector(".js-plotly-plot, svg.main-svg", timeout=30_000)
                page.wait_for_timeout(1500)
                page.screenshot(path=shot)
            names = page.evaluate(ROW_JS, "Run Name:")
            modes = page.evaluate(ROW_JS, "cell.mode")
            success = page.evaluate(METRIC_JS, "success")
            assert names and modes and success, (names, modes, success)
            assert sorted(zip(names, modes, success, strict=True)) == sorted(
                (name, mode, pct) for name, (mode, pct) in expected.items()
            )
            # the UI opens in its model-training view, not GenAI
            assert page.get_by_text("Model training").count() >= 1
            browser.close()
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=30)
