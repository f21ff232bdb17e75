"""The import boundaries of the design, checked on the source (AST), so a change that crosses
one fails here instead of in a review: pipeline/ imports workers/, never the reverse; envs/ and
backbones/ never import each other; training/ and tests/ are imported by nothing shipped; the
method's distribution (lerobot_policy_idr/) imports nothing of the harness, and its idr_core
nothing of lerobot."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

# package folder -> module prefixes its code must never import
FORBIDDEN = {
    "workers": ("pipeline", "training", "tests"),
    "workers/envs": ("workers.backbones", "workers.experts", "workers.actor"),
    "workers/backbones": ("workers.envs", "workers.experts", "workers.actor"),
    "pipeline": ("training", "tests"),
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
