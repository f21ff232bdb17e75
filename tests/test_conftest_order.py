"""The list of long test files that xdist starts first names files that exist (a renamed file
would silently fall back to the end of the queue, where it makes the tail)."""

from __future__ import annotations

from pathlib import Path

from tests.conftest import LONG_FIRST

ROOT = Path(__file__).resolve().parents[1]


def test_every_long_first_file_exists_once() -> None:
    missing = [p for p in LONG_FIRST if not (ROOT / p).is_file()]
    assert not missing, f"tests/conftest.py LONG_FIRST names missing files: {missing}"
    assert len(set(LONG_FIRST)) == len(LONG_FIRST)


def test_collection_puts_the_long_files_first(pytestconfig) -> None:

    class Item:
        def __init__(self, nodeid: str) -> None:
            self.nodeid = nodeid

    from tests.conftest import pytest_collection_modifyitems

    items = [Item("tests/test_a.py::t1"), Item(f"{LONG_FIRST[1]}::t"), Item("tests/test_a.py::t2"),
             Item(f"{LONG_FIRST[0]}::t")]  # fmt: skip
    pytest_collection_modifyitems(pytestconfig, items)  # type: ignore[arg-type]
    assert [i.nodeid for i in items] == [
        f"{LONG_FIRST[0]}::t", f"{LONG_FIRST[1]}::t", "tests/test_a.py::t1", "tests/test_a.py::t2"
    ]  # fmt: skip
