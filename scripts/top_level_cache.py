"""Write each installed distribution's ``top_level.txt`` where its wheel has none (run by
scripts/setup.sh after installing, with the venv's interpreter).

Why: transformers and diffusers call ``importlib.metadata.packages_distributions()`` when
imported, so every process that loads a lerobot policy (each Ray actor, CLI call,
lerobot-eval) calls it twice. For a distribution without ``top_level.txt`` (most wheels uv
installs) the standard library infers the names by reading its RECORD and stat-ing every file
it lists: about 30,000 files in this venv, 1.2 s a call on a 2-core AMD EPYC. With the files
written, a call reads them (0.17 s).

The names written are the standard library's own inference (``_top_level_inferred``), so the
mapping ``packages_distributions()`` returns is unchanged (``tests/scripts`` checks it), and
each file is listed in its distribution's RECORD, so uninstalling or upgrading the
distribution removes it with the rest.

    python scripts/top_level_cache.py        # prints how many files it wrote
"""

from __future__ import annotations

import importlib.metadata as md
from pathlib import Path

NAME = "top_level.txt"
#: the standard library's inference (Python 3.10-3.13); None in a Python without it
_INFER = getattr(md, "_top_level_inferred", None)


def inferred(dist: md.Distribution) -> list[str]:
    """The top-level names the standard library infers for ``dist`` (sorted)."""
    return sorted(_INFER(dist)) if _INFER is not None else []


def write_missing(dists: list[md.Distribution] | None = None) -> int:
    """Writes ``top_level.txt`` for each distribution (default: all installed) that lacks one
    and has a writable ``.dist-info`` folder with a RECORD; the number written."""
    if _INFER is None:
        return 0  # another Python's importlib.metadata: nothing known to be equal to write
    written = 0
    for dist in md.distributions() if dists is None else dists:
        folder = getattr(dist, "_path", None)
        if not isinstance(folder, Path) or folder.suffix != ".dist-info":
            continue
        record = folder / "RECORD"
        if dist.read_text(NAME) is not None or not record.is_file():
            continue
        (folder / NAME).write_text("".join(f"{name}\n" for name in inferred(dist)))
        ends_in_newline = record.read_bytes().endswith(b"\n")
        with record.open("a") as f:  # a row of PEP 376's csv, with no hash, as RECORD's own
            f.write(f"{'' if ends_in_newline else chr(10)}{folder.name}/{NAME},,\n")
        written += 1
    return written


if __name__ == "__main__":
    print(write_missing())
