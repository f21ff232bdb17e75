"""``lerobot-idr-mark DIAG_DIR success|failure``: the operator's verdict on the episode running.

lerobot-rollout's keys end, re-record or stop an episode but mark no success, and a robot has no
``info["is_success"]``. Run this from a second terminal (or bind it to a key or foot pedal) the
moment the task is done: it appends ``{wall_time, outcome}`` to ``DIAG_DIR/marks.jsonl``, and
``idr-eval sidecar`` gives the mark to the episode that was running then, so completion time is
the wall time from that episode's first chunk request to the mark (the robot's waits on
inference included).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

MARKS = "marks.jsonl"
OUTCOMES = ("success", "failure")


def mark(directory: Path, outcome: str, when: float | None = None) -> dict:
    if outcome not in OUTCOMES:
        raise ValueError(f"outcome {outcome!r} is unknown; use one of {OUTCOMES}")
    if not directory.is_dir():
        raise ValueError(
            f"DIAG_DIR {directory} does not exist: give the diagnostics folder the policy "
            "announced at the start of the rollout"
        )
    record = {"wall_time": time.time() if when is None else when, "outcome": outcome}
    line = json.dumps(record) + "\n"
    fd = os.open(directory / MARKS, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        os.write(fd, line.encode())  # one write of one line: concurrent marks never interleave
    finally:
        os.close(fd)
    return record


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="lerobot-idr-mark", description=__doc__.splitlines()[0])
    p.add_argument("diag_dir", type=Path)
    p.add_argument("outcome", choices=OUTCOMES)
    args = p.parse_args(argv)
    try:
        rec = mark(args.diag_dir, args.outcome)
    except ValueError as e:
        print(f"lerobot-idr-mark: error: {e}", file=sys.stderr)
        return 2
    print(
        f"{rec['outcome']} marked at {time.strftime('%H:%M:%S', time.localtime(rec['wall_time']))}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
