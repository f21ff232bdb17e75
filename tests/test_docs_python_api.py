"""docs/python-api.md's examples run: its python blocks, in order, as one script in a fresh
interpreter from the repository root (an example that stops working fails here)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "python-api.md"
BLOCK = re.compile(r"^```python\n(.*?)^```$", re.S | re.M)


def python_blocks(text: str) -> list[str]:
    """The fenced ```python blocks of a Markdown page, in order."""
    return BLOCK.findall(text)


def test_blocks_are_found() -> None:
    text = "a\n```python\nx = 1\n```\n```bash\nls\n```\n```python\nprint(x)\n```\n"
    assert python_blocks(text) == ["x = 1\n", "print(x)\n"]


@pytest.mark.slow  # a smoke run twice and a lerobot policy loaded twice
def test_the_python_api_page_runs(tmp_path: Path) -> None:
    blocks = python_blocks(PAGE.read_text())
    script = "\n".join(blocks)
    assert len(blocks) >= 5
    assert "evaluate(" in script and "diagnose(" in script
    env = {**os.environ, "MPLBACKEND": "Agg"}
    r = subprocess.run(
        [sys.executable, "-c", script],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    assert "12 episodes stored in" in r.stdout
    assert "executor.wrokers: unknown key; did you mean 'workers'?" in r.stdout
    r_img = re.search(r"R_img (\d\.\d+) \[(\d\.\d+), (\d\.\d+)\] over 8 frames", r.stdout)
    assert r_img is not None, r.stdout
    mean, lo, hi = map(float, r_img.groups())
    assert 0 <= lo <= mean <= hi <= 1
