"""The confirmatory study's results as data: a study dir's ``observations.json`` (its declared
endpoints with Holm, the exploratory comparisons, each member pooled over its training seeds,
each run's figures) with what a reader checks the claim by, into
``benchmarks/results/confirmatory_metaworld.json`` (docs/zoo.md renders it).

    python benchmarks/confirmatory_study.py STUDY_DIR [--study conf/paper/confirmatory.yaml] [--out PATH] [--merge]

Added beside the study's figures: the study file's last commit and its date against the first
episode's start (``declared_before_data``: the file, endpoints included, was committed before
any episode ran and not changed since), the endpoints' pinned hash, each run's tau and the
episodes it was fitted on, the episodes' hardware and code versions, the first to last
episode's wall span, and this machine's record.

``--merge`` adds a study dir's members to the file's (a study run member by member, on machines
or sessions apart, with ``idr-eval study --only``): a member the study dir ran replaces the file's,
the others are kept; each primary endpoint is taken from where its member ran, and Holm's
adjustment is computed again over the declared family from the endpoints' raw p-values (one not
run still counting as p = 1). Files of another study file or endpoints hash are refused.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from datetime import datetime
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from pipeline.reporting.endpoints import family_holm  # noqa: E402
from pipeline.reporting.observations import rimg_vs_gain  # noqa: E402
from pipeline.results.calibration import read_calibration  # noqa: E402
from pipeline.results.store import RunStore  # noqa: E402
from workers.hardware import machine_record  # noqa: E402

STUDY = Path("conf/paper/confirmatory.yaml")
OUT = ROOT / "benchmarks" / "results" / "confirmatory_metaworld.json"
EPISODE_COLUMNS = ["started_at", "finished_at", "hardware", "code_version", "error"]


def declaration(study: Path, repo: Path = ROOT) -> dict[str, str]:
    """The study file's last commit in ``repo`` (hash and ISO date); refuses a file with
    changes not committed, which would not be the declared one."""
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--", str(study)],
        cwd=repo,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.strip()
    if dirty:
        raise SystemExit(f"{study}: has changes not committed; the declared study is its commit")
    out = subprocess.run(
        ["git", "log", "-1", "--format=%H %cI", "--", str(study)],
        cwd=repo,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    if len(out) != 2:
        raise SystemExit(f"{study}: not committed; a study is declared by committing its file")
    return {"commit": out[0], "committed_at": out[1]}


def run_record(run_dir: Path) -> dict[str, object]:
    """What a run's episodes say about where and when they ran, and its tau."""
    eps = RunStore(run_dir, read_only=True).episodes(columns=EPISODE_COLUMNS).to_pandas()
    return {
        "episodes": len(eps),
        "errors": int(eps["error"].notna().sum()),
        "first_started_at": str(eps["started_at"].min()),
        "last_finished_at": str(eps["finished_at"].max()),
        "hardware": sorted(set(eps["hardware"].dropna())),
        "code_versions": sorted(set(eps["code_version"].dropna())),
        "tau": read_calibration(run_dir),
    }


def _member(label: str) -> str:
    return label.split(":seed", 1)[0]


def merge(old: dict, new: dict) -> dict:
    """``new``'s members over ``old``'s (see the module's docstring)."""
    for key in ("study_file", "commit", "endpoints_hash"):
        if old.get(key) != new.get(key):
            raise SystemExit(
                f"--merge: the file holds {key} {old.get(key)!r}, this study {new.get(key)!r}; "
                "results of two declarations are never merged: write to another --out"
            )
    ran = {_member(label) for label in new["run_records"]}
    keep = {k: v for k, v in old["run_records"].items() if _member(k) not in ran}
    out = dict(new)
    out["run_records"] = {**keep, **new["run_records"]}
    out["runs"] = [r for r in old["runs"] if f"{r['arch']}@{r['env']}" not in ran] + new["runs"]
    out["members"] = [m for m in old["members"] if m["member"] not in ran] + new["members"]
    primary = [
        n if n["ran"] or not o["ran"] else o
        for o, n in zip(old["comparisons"]["primary"], new["comparisons"]["primary"], strict=True)
    ]
    for r, p in zip(primary, family_holm(primary), strict=True):
        r["p_holm"] = p
    exploratory = [
        r for r in old["comparisons"]["exploratory"] if _member(r["member"]) not in ran
    ] + new["comparisons"]["exploratory"]
    out["comparisons"] = {"primary": primary, "exploratory": exploratory}
    out["rimg_vs_gain"] = rimg_vs_gain(out["runs"])
    out["first_episode_at"] = min(old["first_episode_at"], new["first_episode_at"])
    out["declared_before_data"] = old["declared_before_data"] and new["declared_before_data"]
    out["wall_minutes"] = old["wall_minutes"] + new["wall_minutes"]
    machines = [m for m in old.get("machines", [old["machine"]]) if m != new["machine"]]
    out["machines"] = [*machines, new["machine"]]
    return out


def _time(text: str) -> datetime:
    t = datetime.fromisoformat(text)
    return t if t.tzinfo else t.astimezone()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("study_dir", type=Path)
    p.add_argument("--study", type=Path, default=STUDY)
    p.add_argument("--out", type=Path, default=OUT)
    p.add_argument("--merge", action="store_true", help="add this study dir's members to --out's")
    args = p.parse_args(argv)
    obs_file = args.study_dir / "observations.json"
    if not obs_file.is_file():
        p.error(f"{obs_file}: not found; run `idr-eval study {args.study} --out {args.study_dir}`")
    result = json.loads(obs_file.read_text())
    declared = declaration(args.study)
    runs = {
        f"{r['arch']}@{r['env']}:seed{r['seed']}": run_record(
            args.study_dir / Path(r["run_dir"]).name
        )
        for r in result["runs"]
    }
    first = min(_time(str(r["first_started_at"])) for r in runs.values())
    last = max(_time(str(r["last_finished_at"])) for r in runs.values())
    data = {
        "label": "confirmatory",
        "study_file": str(args.study),
        **declared,
        "first_episode_at": first.isoformat(),
        "declared_before_data": _time(declared["committed_at"]) < first,
        "endpoints_hash": result.get("endpoints_hash"),
        "wall_minutes": (last - first).total_seconds() / 60,
        "machine": machine_record(),
        "run_records": runs,
        **{k: v for k, v in result.items() if k != "endpoints_hash"},
    }
    if args.merge and args.out.exists():
        data = merge(json.loads(args.out.read_text()), data)
    args.out.write_text(json.dumps(data, indent=1, default=str) + "\n")
    print(
        f"wrote {args.out}: {len(runs)} runs, declared before data: {data['declared_before_data']}"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
