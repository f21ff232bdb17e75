"""The documentation: the site builds with --strict (a broken link fails it), the README stays short
and its links resolve, the generated tables carry the figures of benchmarks/results/*.json, and
the pages say what is true now, not how it came to be."""

from __future__ import annotations

import html
import importlib.util
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest
import yaml
from mkdocs.exceptions import PluginError

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
RESULTS = ROOT / "benchmarks" / "results"
README_MAX_LINES = 150

# development history has no place in the docs; legitimate words ("process", "issues a request")
# must not trip these
HISTORY = [
    re.compile(p, re.IGNORECASE)
    for p in (
        r"\bsession\b",
        r"\bissue \d+",
        r"\bissue #\d+",
        r"before the fix",
    )
]


def _mkdocs_build(config: Path, site: Path) -> subprocess.CompletedProcess[str]:
    cmd = [sys.executable, "-m", "mkdocs", "build", "--strict", "-f", str(config), "-d", str(site)]
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300, check=False)


def _hook() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "results_tables", DOCS / "hooks/results_tables.py"
    )
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _text(page: Path) -> str:
    """A built page's visible text, whitespace collapsed."""
    body = re.sub(r"<script.*?</script>|<style.*?</style>", " ", page.read_text(), flags=re.S)
    return re.sub(r"\s+", " ", html.unescape(re.sub(r"<[^>]+>", " ", body)))


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The site, built once with --strict."""
    out = tmp_path_factory.mktemp("site")
    proc = _mkdocs_build(ROOT / "mkdocs.yml", out)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return out


def test_the_site_builds_strict(site: Path) -> None:
    for page in ("index.html", "architecture/index.html", "guarantees/index.html"):
        assert (site / page).is_file(), page


def test_a_broken_link_fails_the_strict_build(tmp_path: Path) -> None:
    """The repository's validation settings turn a missing page or anchor into a failure."""
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    docs = tmp_path / "docs"
    docs.mkdir()
    (docs / "index.md").write_text("# Home\n\n[gone](missing.md) and [here](#no-such-anchor)\n")
    config.update(docs_dir=str(docs), nav=["index.md"], hooks=[], exclude_docs="")
    (tmp_path / "mkdocs.yml").write_text(yaml.safe_dump(config))
    proc = _mkdocs_build(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert proc.returncode != 0
    assert "missing.md" in proc.stdout + proc.stderr


def test_the_readme_is_short_and_its_links_resolve() -> None:
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= README_MAX_LINES
    links = re.findall(r"\]\(([^)\s]+)\)", text)
    assert links
    relative = [link for link in links if not re.match(r"[a-z]+://|mailto:|#", link)]
    missing = [link for link in relative if not (ROOT / link.split("#")[0]).exists()]
    assert not missing, missing


def test_the_fault_table_is_generated_from_its_json(site: Path) -> None:
    faults = json.loads((RESULTS / "faults.json").read_text())
    text = _text(site / "guarantees/index.html")
    assert f"{len(faults['faults'])} faults" in text
    for name, value in faults["totals"].items():
        assert f"{name.replace('_', ' ')} {value}" in text
    for fault in faults["faults"]:
        assert fault["fault"] in text


def test_a_benchmark_table_carries_its_json_figures(site: Path) -> None:
    hook = _hook()
    cluster = json.loads((RESULTS / "cluster.json").read_text())
    text = _text(site / "benchmarks/index.html")
    assert f"({hook.num(cluster['throughput']['speedup'])}x)" in text
    passes = json.loads((RESULTS / "idr_passes.json").read_text())
    act = passes["backbones"]["lerobot_act_96px"]
    assert f"{hook.num(act['ratio_batched_vs_single'])}x" in text


def test_an_unknown_marker_raises() -> None:
    hook = _hook()
    with pytest.raises(PluginError, match="no_such_results"):
        hook.on_page_markdown("x\n<!-- results: no_such_results -->\n", None, None, None)


def test_a_missing_results_file_raises(tmp_path: Path) -> None:
    with pytest.raises(PluginError, match="does not exist"):
        _hook().render("faults", results=tmp_path)


def test_every_renderer_renders_its_file() -> None:
    hook = _hook()
    for name in hook.RENDERERS:
        assert "|---" in hook.render(name), name


def test_no_page_tells_development_history() -> None:
    pages = sorted(DOCS.rglob("*.md"))
    assert pages
    found = [
        f"{page.relative_to(ROOT)}:{n}: {line.strip()}"
        for page in pages
        for n, line in enumerate(page.read_text().splitlines(), 1)
        if any(p.search(line) for p in HISTORY)
    ]
    assert not found, found


def test_every_benchmark_names_its_machine_by_the_cpu_model() -> None:
    """A result's machine comes from workers.hardware.machine_record (the CPU model and the
    instruction set torch dispatches to), not a hand-made dict."""
    writers = [
        p.name
        for p in sorted((ROOT / "benchmarks").glob("*.py"))
        if '"machine":' in p.read_text()
        and not re.search(r"machine_record\(|_machine\(|\bmachine\(\)", p.read_text())
    ]
    assert not writers, writers


def test_a_results_caption_names_the_cpu_or_says_it_was_not_recorded() -> None:
    hook = _hook()
    line = hook.machine(
        {"machine": {"cpu_model": "AMD EPYC 7B13", "cpu_capability": "AVX2", "cpus": 2}}
    )
    assert line.startswith("AMD EPYC 7B13, torch dispatching AVX2, 2 CPUs")
    assert hook.machine({"machine": {"cpus": 2}}).endswith("(CPU model not recorded)")
    assert hook.machine({"machine": "x86_64"}) == "x86_64 (CPU model not recorded)"
    for path in sorted((ROOT / "benchmarks" / "results").glob("*.json")):
        data = json.loads(path.read_text())
        if isinstance(data, dict) and data.get("machine"):
            text = hook.machine(data)
            cpu = data["machine"].get("cpu_model") if isinstance(data["machine"], dict) else None
            assert (cpu and cpu in text) or "not recorded" in text, path.name


# a time measured in prose: "8 min 33 s", "0.21-0.25 s", "~160 ms at batch 64"
_MEASURED = re.compile(r"\d(?:[\d.,]*)\s?(?:ms|min|minutes|s per|s a step)\b")
_MACHINE = re.compile(r"EPYC|Xeon|Ryzen|Core i\d|H100|H200|A100|results:")


def test_every_page_of_measured_figures_names_the_machine() -> None:
    """A page that quotes measured times names the CPU (or GPU) they were measured on, or
    renders them from a results file whose caption does."""
    missing = [
        str(page.relative_to(ROOT))
        for page in sorted(DOCS.rglob("*.md"))
        if _MEASURED.search(page.read_text()) and not _MACHINE.search(page.read_text())
    ]
    assert not missing, missing
