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


# -- figures quoted in prose come from their results files ---------------------------------------

# pages that quote the zoo's and the observations study's figures
FIGURE_PAGES = ("zoo.md",)

# a results quantity: a decimal (R_img, E_img, τ, a p-value, an error), a percentage, a difference
# in pp, a count of successes ("8/40", "44 of 50"), a p- or ρ-value, an interval's bound, a signed
# change; a bare integer is a count or a setting (episodes, steps, seeds) and is not one
_RESULT = re.compile(
    r"[−+]?\d+(?:\.\d+)?(?:e[−-]?\d+)?\s?(?:%|pp\b)"  # 88%, +4.0 pp
    r"|\d+(?:\.\d+)?e[−-]?\d+"  # 1e-4
    r"|(?<![\w.])\d+\.\d+(?![\w.]*\w)"  # 0.435 (not 0.6.1, not pi0.5)
    r"|\b\d+\s?(?:/|of)\s?\d+\b"  # 8/40, 44 of 50
    r"|(?:\bp|ρ|τ)\s?[=<>≈]\s?[−+-]?\d+(?:\.\d+)?(?:e[−-]?\d+)?"  # p = 1, τ = 1.73
    r"|\[[−+-]?\d+(?:\.\d+)?,"  # [0, +10]
    r"|(?<![\w.])[−+]\d+(?:\.\d+)?"  # −2 episodes
)
# what follows a figure that is no result: a unit of time, size or resolution, a count of things
_UNIT = re.compile(
    r"\s?-?(?:steps?|s|ms|min|minutes?|hours?|MB|KB|MiB|GB|GiB|px|Hz|M|K|x|d|frames|parameters"
    r"|cores?|threads?|layers?|tokens?|workers?|cameras?|passes)\b"
)
# what precedes a setting: a flag in a code span (its value follows), a named hyperparameter
_SETTING = re.compile(
    r"(?:§|\b(?:seed|batch|widths?|std|rate|lerobot|version|indices|dims)|[αβλ])\s*\(?$"
)
# a confidence level is a setting too: "a 95% interval"
_LEVEL = re.compile(r"\s(?:interval|CI|confidence)")


def _prose(text: str) -> str:
    """The page without what is not prose: fenced code (lines kept, blanked), code spans, figure
    and results markers, HTML comments, link targets; a removed code span leaves ``§``."""
    text = re.sub(r"^```.*?^```", lambda m: "\n" * m.group(0).count("\n"), text, flags=re.S | re.M)
    text = re.sub(r"<!--.*?-->", "", text, flags=re.S)
    text = re.sub(r"\{\{.*?\}\}", "⟦⟧", text, flags=re.S)
    text = re.sub(r"`[^`\n]*`", "§", text)
    return re.sub(r"\]\([^)\s]*\)", "]", text)


def hand_typed_results(text: str) -> list[str]:
    """Every results quantity typed by hand in ``text``, as ``LINE: figure``."""
    found = []
    lines = _prose(text).splitlines()
    for n, line in enumerate(lines, 1):
        for m in _RESULT.finditer(line):
            # a phrase may run on over a line break
            before = (lines[n - 2] + " " if n > 1 else "") + line[: m.start()]
            after = line[m.end() :] + (" " + lines[n] if n < len(lines) else "")
            figure = m.group(0)
            if (
                _SETTING.search(before)
                or (figure[-1].isdigit() and _UNIT.match(after))
                or (figure.endswith("%") and _LEVEL.match(after))
            ):
                continue
            found.append(f"{n}: {m.group(0)!r} in {line.strip()[:100]!r}")
    return found


@pytest.mark.parametrize("page", FIGURE_PAGES)
def test_every_results_figure_a_page_quotes_is_rendered_from_its_json(page: str) -> None:
    """A success rate, R_img, E_img, pp difference, p-value or interval in the zoo's prose is a
    ``{{ NAME:PATH | OPS }}`` marker that the docs hook fills from benchmarks/results/NAME.json,
    never a number typed by hand (which drifts from its file)."""
    found = hand_typed_results((DOCS / page).read_text())
    assert not found, "\n".join(found)


def test_the_scan_finds_typed_figures_and_passes_settings() -> None:
    typed = (
        "R_img 0.42 (E_img 1.51); 44 of 50, 88% [76, 94]; −3.3 pp [−8.3, 0], p = 1; 8/40 "
        "and τ = 1.73; p = 1e-4"
    )
    assert [f.split("'")[1] for f in hand_typed_results(typed)] == [
        "0.42", "1.51", "44 of 50", "88%", "[76,", "−3.3 pp", "[−8.3,", "p = 1", "8/40",
        "τ = 1.73", "p = 1e-4",
    ]  # fmt: skip
    settings = (
        "3,000 steps at batch 64, seed 1, 47 minutes, 2.4 minutes, 1.9 MB, 96 px, 20 Hz, "
        "17.1M parameters, std 0.3, α 0.08, learning rate (3e-4), lerobot 0.6.1, pi0.5, "
        "a 95%\ninterval, about 1.5 passes over the frames, "
        "`--steps 3000` and `state_noise` 0.1, widths 64/128/256, {{ zoo:a.b | .2f }} "
        "<!-- results: zoo_tabletop -->\n```bash\nx 0.5 44/50\n```"
    )
    assert hand_typed_results(settings) == []


def test_a_figure_marker_renders_its_json_value(tmp_path: Path) -> None:
    hook = _hook()
    (tmp_path / "r.json").write_text(
        json.dumps(
            {
                "members": {
                    "a": {
                        "r_img": 0.4348,
                        "ci95": [0.41, 0.46],
                        "diff": -0.0333,
                        "tasks": [
                            {"cell": "diagnose", "task": "t1", "successes": 10, "n": 10},
                            {"cell": "diagnose", "task": "t2", "successes": 34, "n": 40},
                            {"cell": "E", "task": "t1", "successes": 0, "n": 10},
                        ],
                    }
                }
            }
        )
    )

    def fig(path: str, ops: str = "") -> str:
        return hook.figure("r", path, ops, results=tmp_path)

    assert fig("members.a.r_img") == "0.435"
    assert fig("members.a.r_img", ".2f") == "0.43"
    assert fig("members.a.ci95", ".2f") == "[0.41, 0.46]"
    assert fig("members.a.diff", "x100 +.1f") == "\u22123.3"
    assert fig("members.a.tasks[cell=diagnose].successes", "sum") == "44"
    assert fig("members.a.tasks[cell=diagnose]", "rate .0%") == "88%"
    assert fig("members.a.tasks[cell=diagnose]", "wilson x100 .0f") == "[76, 94]"
    assert fig("members.a.tasks[cell=E,task=t1].successes", "one") == "0"
    assert fig("members.a.ci95", "range .2f") == "0.41-0.46"
    for path, ops in (
        ("members.b.r_img", ""),
        ("members.a.tasks[cell=A].n", "sum"),
        ("members.a.tasks[cell=diagnose].n", ""),
        ("members.a.r_img", "frobnicate .2f"),
    ):
        with pytest.raises(PluginError, match="figure r:"):
            fig(path, ops)
    hook.RESULTS = tmp_path
    page = "R_img {{ r:members.a.r_img | .2f }} {{r:members.a.ci95|.2f}}, `{{ as code }}`"
    assert (
        hook.on_page_markdown(page, None, None, None) == "R_img 0.43 [0.41, 0.46], `{{ as code }}`"
    )
    with pytest.raises(PluginError, match="does not exist"):
        hook.on_page_markdown(page.replace("r:", "gone:"), None, None, None)


def test_the_zoo_page_shows_its_json_figures_and_no_marker(site: Path) -> None:
    hook = _hook()
    text = _text(site / "zoo/index.html")
    assert "{{" not in text and "}}" not in text
    tabletop = json.loads((RESULTS / "zoo_tabletop.json").read_text())["members"]
    assert f"R_img {hook.num(tabletop['tiny_vla']['diagnose_effects']['r_img'])} " in text
    assert f"R_img {hook.num(tabletop['xvla']['diagnose_effects']['r_img'])} " in text
