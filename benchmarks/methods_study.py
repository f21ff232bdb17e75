"""The test-time methods measured side by side: each run dir's methods table as data, into
``benchmarks/results/methods.json`` (docs/methods.md renders it).

    python benchmarks/methods_study.py LABEL=RUN_DIR [LABEL=RUN_DIR ...] [--out PATH] [--merge]

The file holds ``runs.<LABEL>.cells.<CELL>``: each cell's success, its pairings and its cost.
``LABEL`` names the policy and the benchmark (``tiny_vla_tabletop``, ``smolvla_seed1_metaworld``...); a run dir holds one
backbone on one suite and several methods as values of ``mode`` (conf/grids/methods.yaml on
the tabletop; conf/zoo/metaworld.yaml with a methods grid on MetaWorld). The figures are
exploratory: no comparison was declared before its data. ``--merge`` keeps the runs the file
already holds under other labels (their run dirs need not be here) and replaces those given.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.reporting.methods import methods_summary  # noqa: E402
from pipeline.results.calibration import read_calibration  # noqa: E402
from pipeline.results.store import RunStore  # noqa: E402
from pipeline.rundir import read_run_json  # noqa: E402

OUT = ROOT / "benchmarks" / "results" / "methods.json"
STEP_COLUMNS = ["cell_id", "pass_rows", "executed_steps", "inference_ms"]


def summarize(member: str, run_dir: Path) -> dict:
    store = RunStore(run_dir, read_only=True)
    meta = read_run_json(run_dir) or {}
    episodes = store.episodes().to_pandas()
    (run,) = methods_summary(episodes, store.steps(columns=STEP_COLUMNS))
    hardware = sorted(set(episodes["hardware"].dropna()))
    per_task = episodes.groupby(["cell_id", "task_id"]).size()
    return {
        "member": member,
        "run_dir": run_dir.name,
        "episodes_per_task": int(per_task.max()),
        "errors": int(episodes["error"].notna().sum()),
        "hardware": hardware,
        "numerics": sorted(set(episodes["numerics"].dropna())),
        "tau": read_calibration(run_dir),
        "config": yaml.safe_load((run_dir / "config.yaml").read_text()),
        "code_version": meta.get("code_version"),
        "run_hardware": meta.get("hardware"),  # what run.json recorded per hardware class
        **run,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument(
        "--merge", action="store_true", help="keep the runs --out holds under other labels"
    )
    args = p.parse_args(argv)
    runs = {}
    if args.merge and args.out.exists():
        runs = dict(json.loads(args.out.read_text())["runs"])
    for item in args.runs:
        member, _, path = item.partition("=")
        if not path or not Path(path).is_dir():
            p.error(f"{item!r}: write LABEL=RUN_DIR with an existing run dir")
        run = summarize(member, Path(path))
        # keyed, so that the docs quote a figure by its path: runs.<member>_<suite>.cells.<cell>
        run["cells"] = {c["cell"]: c for c in run["cells"]}
        runs[member] = run
    data = {
        "label": "exploratory",
        "declared_before_data": False,
        "runs": runs,
    }
    args.out.write_text(json.dumps(data, indent=1, default=str) + "\n")
    print(f"wrote {args.out} ({len(runs)} runs)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
