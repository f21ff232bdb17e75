"""The import boundaries of the design, checked on the source (AST), so a change that crosses
one fails here instead of in a review: pipeline/ imports workers/, never the reverse; envs/ and
backbones/ never import each other; training/ and tests/ are imported by nothing shipped (the
benchmarks included: the fakes and toy checkpoints they share with the tests are shipped); the
method's distribution (lerobot_policy_idr/) imports nothing of the harness, and its idr_core
nothing of lerobot.

workers/ is in rooms, each importing only its own and the ones below it (``WORKERS_ROOMS``):

0. the modules loose at its top (registry, params, io_spec, rendering, hardware, safe_load,
   worker_log): what every room shares; they import no room;
1. ``envs/`` and ``backbones/`` (never each other);
2. ``experts/`` (scripted experts on an env's privileged state);
3. ``policy/`` (the wrapper, the shared service, its actor, socket and client): never the
   episode side;
4. ``episode/`` (the episode worker, its rows, observations and videos): steps an env with
   the policy side's wrapper or client.

And the house stays walkable: at most eight modules loose at workers/ top, no module of workers/
over 450 lines nor function over 80 (but those ``SPLIT_PENDING`` names)."""

from __future__ import annotations

import ast
import re
from collections.abc import Callable
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# package folder -> module prefixes its code must never import
FORBIDDEN = {
    "workers": ("pipeline", "training", "tests"),
    "workers/envs": ("workers.backbones", "workers.experts"),
    "workers/backbones": ("workers.envs", "workers.experts"),
    "pipeline": ("training", "tests"),
    "training": ("tests",),
    # shipped scripts: what they time stands on shipped code (fakes, toy checkpoints), not tests/
    "benchmarks": ("tests",),
    # the method's own distribution installs on a robot computer without the harness
    "lerobot_policy_idr": ("workers", "pipeline", "training", "tests", "benchmarks"),
    # the method on arrays: no model, no simulator, no lerobot (torch only lazily, for torch
    # inputs; test_configuration_idr checks that importing it loads neither)
    "lerobot_policy_idr/src/idr_core": ("lerobot", "lerobot_policy_idr", "mujoco"),
}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("folder", sorted(FORBIDDEN))
def test_no_module_crosses_a_boundary(folder) -> None:
    banned = FORBIDDEN[folder]
    files = sorted((ROOT / folder).rglob("*.py"))
    assert files, folder
    crossings = [
        f"{f.relative_to(ROOT)} imports {name}"
        for f in files
        for name in sorted(_imports(f))
        if any(name == b or name.startswith(b + ".") for b in banned)
    ]
    assert not crossings, crossings


# pipeline/ in layers: a module imports its own layer and the ones below, never one above
# (the report <-> figures circle of the flat layout is what this catches). Lazy imports inside
# functions count too: a circle through a function is still a circle.
PIPELINE_LAYERS = (
    ("pipeline.errors", "pipeline.rundir"),  # the two kinds of error; the run dir's names
    ("pipeline.planning",),  # config, grid, plan, checkpoint fit: nothing run yet
    ("pipeline.results",),  # the store and the statistics over it
    ("pipeline.reporting",),  # markdown, figures, HTML slices, compare: views of results
    ("pipeline.tracking",),  # MLflow: logs the same views
    ("pipeline.execution",),  # runner, scheduler, writer, executors, cluster
    ("pipeline.api",),  # evaluate / diagnose from Python: what the CLI's run calls
    # the commands: the parser and main, one module per command group
    (
        "pipeline.cli",
        "pipeline.cli_run",
        "pipeline.cli_study",
        "pipeline.cli_results",
        "pipeline.cli_ui",
        "pipeline.cli_list",
        "pipeline.cli_reliance",
    ),
)


def _layer(module: str) -> int | None:
    for i, prefixes in enumerate(PIPELINE_LAYERS):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return i
    return None


def _upward(package: str, level: Callable[[str], int | None], word: str) -> list[str]:
    """Imports in ``package`` of a module at a higher ``level`` than the importer's."""
    upward = []
    for f in sorted((ROOT / package).rglob("*.py")):
        mod = ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        own = level(mod)
        if own is None:
            continue
        for name in sorted(_imports(f)):
            theirs = level(name)
            if theirs is not None and theirs > own:
                upward.append(f"{mod} ({word} {own}) imports {name} ({word} {theirs})")
    return upward


def test_pipeline_layers_import_only_downwards() -> None:
    upward = _upward("pipeline", _layer, "layer")
    assert not upward, upward


def test_every_pipeline_module_has_a_layer() -> None:
    """A new folder or module is placed in a layer on purpose."""
    unplaced = [
        str(f.relative_to(ROOT))
        for f in sorted((ROOT / "pipeline").rglob("*.py"))
        if f.name != "__init__.py" or f.parent != ROOT / "pipeline"
        if _layer(".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__"))
        is None
    ]
    assert not unplaced, unplaced


def test_suites_do_not_import_each_other() -> None:
    """One folder per suite (workers/envs/suites/<name>/); shared pieces live beside suites/."""
    suites = ROOT / "workers/envs/suites"
    names = [d.name for d in suites.iterdir() if d.is_dir() and d.name != "__pycache__"]
    crossings = [
        f"{f.relative_to(ROOT)} imports {name}"
        for suite in names
        for f in sorted((suites / suite).rglob("*.py"))
        for name in sorted(_imports(f))
        for other in names
        if other != suite
        and (
            name == f"workers.envs.suites.{other}"
            or name.startswith(f"workers.envs.suites.{other}.")
        )
    ]
    assert not crossings, crossings


# a string naming a module of tests/ ("tests.doubles.envs:SlowMarkerEnv", "-m", "tests.x"):
# an import all the same, made by a config, a subprocess or a Ray worker
TESTS_MODULE = re.compile(r"tests(\.\w+)+(:\w+)?")


def test_no_benchmark_names_a_module_of_the_tests() -> None:
    named = [
        f"{f.relative_to(ROOT)}:{node.lineno} names {node.value!r}"
        for f in sorted((ROOT / "benchmarks").rglob("*.py"))
        for node in ast.walk(ast.parse(f.read_text(), filename=str(f)))
        if isinstance(node, ast.Constant) and isinstance(node.value, str)
        if TESTS_MODULE.fullmatch(node.value)
    ]
    assert not named, named


@pytest.mark.parametrize("package", ["pipeline", "training", "workers"])
def test_no_import_circle_between_modules(package) -> None:
    """Within a layer too: modules import one way (lazy imports inside functions included)."""
    graph: dict[str, set[str]] = {}
    for f in sorted((ROOT / package).rglob("*.py")):
        mod = ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")
        graph[mod] = {n for n in _imports(f) if n.startswith(f"{package}.") and n != mod}
    for mod in graph:
        graph[mod] = {n for n in graph[mod] if n in graph}
    seen: dict[str, int] = {}  # 1 on the stack, 2 done
    circles: list[str] = []

    def visit(mod: str, stack: list[str]) -> None:
        seen[mod] = 1
        for dep in sorted(graph[mod]):
            if seen.get(dep) == 1:
                circles.append(" -> ".join([*stack[stack.index(dep) :], dep]))
            elif dep not in seen:
                visit(dep, [*stack, dep])
        seen[mod] = 2

    for mod in sorted(graph):
        if mod not in seen:
            visit(mod, [mod])
    assert not circles, circles


def test_the_driver_actor_contract_imports_no_process_or_socket_code() -> None:
    """``workers.episode.rows`` (specs and rows both sides share) names an env server by its
    ``ServerSpec`` and imports nothing that starts or talks to one."""
    imported = _imports(ROOT / "workers" / "episode" / "rows.py")
    assert "workers.envs.server.spec" in imported
    assert not imported & {"workers.envs.server.client", "socket", "subprocess"}


# workers/ in rooms (the module docstring): a room imports its own and the ones below it. Level 0
# is every module loose at workers/ top.
WORKERS_ROOMS = (
    ("workers.envs", "workers.backbones"),  # 1: never each other (FORBIDDEN)
    ("workers.experts",),  # 2: scripted experts on an env's state
    ("workers.policy",),  # 3: where a policy lives and how requests reach it
    ("workers.episode",),  # 4: an episode stepped into rows, with the policy side's client
)
LOOSE_AT_TOP = {f.stem for f in (ROOT / "workers").glob("*.py") if f.name != "__init__.py"}


def _room(module: str) -> int | None:
    """The level of ``module`` among workers/'s rooms, or None outside workers/ (or a new folder
    no one placed)."""
    parts = module.split(".")
    if parts[0] != "workers" or len(parts) < 2:
        return None
    if parts[1] in LOOSE_AT_TOP:
        return 0
    for i, prefixes in enumerate(WORKERS_ROOMS, start=1):
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return i
    return None


def _workers_module(f: Path) -> str:
    return ".".join(f.relative_to(ROOT).with_suffix("").parts).removesuffix(".__init__")


def test_workers_rooms_import_only_downwards() -> None:
    upward = _upward("workers", _room, "room")
    assert not upward, upward


def test_the_rooms_rule_fails_an_upward_import() -> None:
    """The rule reads a module's room from its path: the policy side importing the episode side,
    or an env the policy side, is upward; the episode side using the policy's client is not."""
    assert _room("workers.policy.actor") < _room("workers.episode.worker")
    assert _room("workers.envs.gym_env") < _room("workers.policy.wrapper")
    assert _room("workers.registry") == 0 < _room("workers.backbones.base")
    assert _room("workers.backbones.base") == _room("workers.envs.base")


def test_every_workers_module_has_a_room() -> None:
    """A new folder of workers/ is placed in a room on purpose."""
    unplaced = [
        str(f.relative_to(ROOT))
        for f in sorted((ROOT / "workers").rglob("*.py"))
        if f != ROOT / "workers" / "__init__.py"
        if _room(_workers_module(f)) is None
    ]
    assert not unplaced, unplaced


MAX_LOOSE_AT_TOP = 8
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 80
# split pending: files another change is editing now; each is split after it lands (then its
# entry goes, and test_split_pending_lists_only_what_is_still_over says so)
SPLIT_PENDING: set[str] = set()  # names over the bounds, each until it is split


def _oversized() -> list[str]:
    """Modules of workers/ over MAX_MODULE_LINES lines ("path") and functions over
    MAX_FUNCTION_LINES ("path::name")."""
    found = []
    for f in sorted((ROOT / "workers").rglob("*.py")):
        rel, text = str(f.relative_to(ROOT)), f.read_text()
        if len(text.splitlines()) > MAX_MODULE_LINES:
            found.append(rel)
        for node in ast.walk(ast.parse(text, filename=rel)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                assert node.end_lineno is not None
                if node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES:
                    found.append(f"{rel}::{node.name}")
    return found


def test_workers_keeps_few_modules_loose_at_its_top() -> None:
    """The rest lives in rooms whose names say what they hold (docs/architecture.md#layout)."""
    assert len(LOOSE_AT_TOP) <= MAX_LOOSE_AT_TOP, sorted(LOOSE_AT_TOP)


def test_no_workers_module_or_function_is_oversized() -> None:
    over = [name for name in _oversized() if name not in SPLIT_PENDING]
    assert not over, (
        f"over {MAX_MODULE_LINES} lines a module or {MAX_FUNCTION_LINES} a function: {over}"
    )


def test_split_pending_lists_only_what_is_still_over() -> None:
    """An entry whose file was split goes, so the list never hides a new one."""
    stale = sorted(SPLIT_PENDING - set(_oversized()))
    assert not stale, f"split already, remove from SPLIT_PENDING: {stale}"


def _oversized_in(package: str) -> list[str]:
    too_long = []
    for f in sorted((ROOT / package).rglob("*.py")):
        text = f.read_text()
        name = f.relative_to(ROOT)
        module_lines = text.count("\n")
        if module_lines > MAX_MODULE_LINES:
            too_long.append(f"{name}: {module_lines} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(text, filename=str(f))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                lines = node.end_lineno - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    too_long.append(
                        f"{name}:{node.lineno} {node.name}: {lines} lines "
                        f"(at most {MAX_FUNCTION_LINES})"
                    )
    return too_long


def test_pipeline_and_training_modules_and_functions_are_small() -> None:
    too_long = [entry for package in ("pipeline", "training") for entry in _oversized_in(package)]
    assert not too_long, too_long
