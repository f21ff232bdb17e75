"""The zoo's model card figures: each member's training record and its evaluation on the zoo
preset (``conf/zoo/tabletop.yaml``), per task and cell with Wilson intervals, mean E_img, E_prop
and R_img of its diagnose cell (pooled over its inferences with a 95% interval, as the
observations study pools it), and E − diagnose paired per member.

Reads ``checkpoints/zoo/[<benchmark>/]<member>/train_meta.json`` and a finished run dir per
member; writes ``benchmarks/results/zoo_<benchmark>.json`` (rendered in docs/zoo.md). A member evaluated again
replaces its entry; the others are kept.

Usage: ``python benchmarks/zoo_card.py [--benchmark metaworld] MEMBER=RUN_DIR [...]``
"""

from __future__ import annotations

import argparse
import json
from datetime import date
from pathlib import Path

import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
PRESETS = {
    "tabletop": "conf/zoo/tabletop.yaml",
    "tabletop_pos": "conf/zoo/tabletop.yaml with env.params.state_dims=[0,1,2,6,7]",
    "metaworld": "conf/zoo/metaworld.yaml",
}


def results_file(benchmark: str, name: str | None = None) -> Path:
    return ROOT / "benchmarks" / "results" / f"{name or f'zoo_{benchmark}'}.json"


def diagnose_effects(run_dir: Path) -> dict:
    """The reference diagnose cell's R_img as the observations study pools it (every inference;
    an interval from resampling episodes), the image-zeroed control left out unless the run holds
    nothing else (a black-images card: E_img 0)."""
    from pipeline.reporting.run_data import load_run, reference_diagnose

    steps = load_run(run_dir).steps
    diag = reference_diagnose(steps)
    if diag is None:
        raise SystemExit(f"{run_dir}: no diagnose cell, so no E_img / E_prop to report")
    return card_effects(
        steps.loc[steps["cell_id"] == diag, ["task_id", "episode_index", "e_img", "e_prop"]].dropna(
            subset=["e_img", "e_prop"]
        )
    )


def card_effects(steps: pd.DataFrame) -> dict:
    """``pooled_effects`` of one diagnose cell's inferences without the image-zeroed control's,
    or of the control's where the run holds nothing else."""
    from pipeline.results.observation_stats import pooled_effects, without_control

    seen = without_control(steps)
    return pooled_effects(seen if len(seen) else steps)


def member_entry(name: str, run_dir: Path, benchmark: str = "tabletop") -> dict:
    from pipeline.results import aggregate as agg
    from pipeline.results.store import RunStore
    from workers.hardware import machine_record

    sub = () if benchmark == "tabletop" else (benchmark,)
    meta_path = ROOT.joinpath("checkpoints", "zoo", *sub, name, "train_meta.json")
    meta = json.loads(meta_path.read_text())
    episodes = RunStore(run_dir, read_only=True).episodes().to_pandas()
    rates = agg.success_by_task(episodes)
    tasks = [
        {
            "cell": r.cell_id,
            "task": r.task_id,
            "n": int(r.n),
            "successes": int(r.successes),
            "errors": int(r.errors),
            "success": float(r.success_rate),
            "ci95": [float(r.ci_low), float(r.ci_high)],
        }
        for r in rates.itertuples()
    ]
    effects = diagnose_effects(run_dir)
    paired = [
        {
            "cell": p.cell_id,
            "n_pairs": p.n_pairs,
            "diff": p.diff,
            "ci95": [p.ci_low, p.ci_high],
            "mcnemar_p": p.p_value,
        }
        for p in agg.paired_vs_baseline(episodes)
    ]
    return {
        "member": name,
        "train": {
            k: meta[k]
            for k in (
                "policy_type",
                "language",
                "params",
                "steps",
                "batch_size",
                "seed",
                "train_seconds",
                "machines",
                "threads",
            )
        }
        # where a GPU trained it, and the float16 carry's measured effect (training/zoo_carry.py)
        | {k: meta[k] for k in ("devices", "carried") if k in meta},
        "eval": {
            "run_dir": run_dir.name,
            "episodes_per_task": int(episodes.groupby(["cell_id", "task_id"]).size().max()),
            "machine": machine_record(),
            "date": date.today().isoformat(),
        },
        "tasks": tasks,
        "diagnose_effects": effects,
        "paired_vs_diagnose": paired,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="MEMBER=RUN_DIR")
    ap.add_argument("--benchmark", choices=sorted(PRESETS), default="tabletop")
    ap.add_argument(
        "--results",
        default=None,
        help="the results file's name (default zoo_BENCHMARK): a card of another evaluation",
    )
    ap.add_argument("--preset", default=None, help="the evaluation, when not the zoo preset")
    args = ap.parse_args()
    results = results_file(args.benchmark, args.results)
    old = json.loads(results.read_text()) if results.is_file() else {"members": {}}
    for item in args.runs:
        name, _, run = item.partition("=")
        entry = member_entry(name, Path(run), args.benchmark)
        before = old["members"].get(name)
        if before is not None and before["eval"]["run_dir"] == entry["eval"]["run_dir"]:
            # the same evaluation carded again: it ran when and where it did
            entry["eval"].update({k: before["eval"][k] for k in ("machine", "date")})
        old["members"][name] = entry
    old["preset"] = args.preset or PRESETS[args.benchmark]
    results.write_text(json.dumps(old, indent=2) + "\n")
    print(json.dumps(old, indent=2)[:3000])


if __name__ == "__main__":
    main()
