"""scripts/top_level_cache.py: the ``top_level.txt`` files it writes are a cache of what the
standard library infers, so ``packages_distributions()`` maps every name as before, and each
file is listed in its RECORD (an uninstall removes it)."""

from __future__ import annotations

import importlib.metadata as md
import importlib.util
from pathlib import Path

import pytest

_SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "top_level_cache.py"
_spec = importlib.util.spec_from_file_location("top_level_cache", _SCRIPT)
top_level_cache = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(top_level_cache)

pytestmark = pytest.mark.skipif(
    not hasattr(md, "_top_level_inferred"), reason="this Python infers no top-level names"
)


def _wheel(root: Path, name: str, files: dict[str, str], record_newline: bool = True) -> Path:
    """An installed distribution as uv leaves one: its files, METADATA and a RECORD."""
    info = root / f"{name}-1.0.dist-info"
    info.mkdir(parents=True)
    (info / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    for rel, text in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(text)
    rows = [f"{rel},," for rel in files] + [f"{info.name}/METADATA,,", f"{info.name}/RECORD,,"]
    (info / "RECORD").write_text("\n".join(rows) + ("\n" if record_newline else ""))
    return info


def test_the_written_names_are_the_inferred_ones_and_listed_in_record(tmp_path) -> None:
    pkg = _wheel(tmp_path, "toy_pkg", {"toy/__init__.py": "", "toy/sub/m.py": "", "solo.py": ""})
    bare = _wheel(tmp_path, "bare", {"bare_mod.py": ""}, record_newline=False)
    dists = [md.PathDistribution(pkg), md.PathDistribution(bare)]
    before = {d.metadata["Name"]: top_level_cache.inferred(d) for d in dists}
    assert before == {"toy_pkg": ["solo", "toy"], "bare": ["bare_mod"]}

    assert top_level_cache.write_missing(dists) == 2
    for d in dists:
        assert d.read_text("top_level.txt").split() == before[d.metadata["Name"]]
        rows = d.read_text("RECORD").splitlines()
        assert f"{d._path.name}/top_level.txt,," in rows  # a row of its own, csv intact
        assert all(row.count(",") == 2 for row in rows)
    assert top_level_cache.write_missing(dists) == 0  # present now: never written twice


def test_the_venvs_mapping_is_the_standard_librarys_inference() -> None:
    """In the venv setup.sh made: every file it wrote holds exactly the inferred names."""
    checked = 0
    for dist in md.distributions():
        record = dist.read_text("RECORD") or ""
        folder = getattr(dist, "_path", Path())
        if f"{folder.name}/top_level.txt,," not in record.splitlines():
            continue  # the wheel's own top_level.txt, or none written
        assert dist.read_text("top_level.txt").split() == top_level_cache.inferred(dist), folder
        checked += 1
    if checked == 0:
        pytest.skip("no top_level.txt written by scripts/top_level_cache.py in this venv")
