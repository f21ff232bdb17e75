"""Reliance over training: the evaluator's ledgers (``RUN/evals/evals.jsonl``, written beside
``python -m training.zoo train ... --eval-every N``) gathered into one results file and a figure.

    python benchmarks/zoo_training.py --run data/zoo/runs/metaworld/tiny_vla_seed1 [--run ...] \
        [--final tiny_vla] [--out PATH] [--figure PATH] [--dry] [--merge]

Per member@seed: every evaluated step with its open-loop R_img (95% interval, episodes
resampled), and where the closed-loop diagnose cell ran its success k/n with the Wilson 95%
interval and its R_img; a step that failed keeps its error, never a number. Beside them the
evaluator's settings (from the run's MLflow params: frames, episodes per task), the training's
record (its config, ``zoo_sessions.jsonl``) and this machine. ``--final MEMBER`` adds the shipped
checkpoint's figures on the same frames (``reliance_<benchmark>.json``, ``zoo_<benchmark>.json``)
as a point of comparison. Writes ``benchmarks/results/zoo_training_<benchmark>.json`` and
``docs/img/zoo_training_<benchmark>.png``; ``--dry`` (a look at a training under way) writes to
a new temporary folder unless ``--out`` / ``--figure`` name paths. ``--merge`` keeps the
member@seed runs and finals the file already holds (their run folders need not be on this
machine) and replaces those given; each run names the machine that gathered it (the ledger
does not record one; the evaluator runs beside training, where the run folder is).
"""

from __future__ import annotations

import argparse
import json
import math
import sqlite3
import sys
from datetime import date
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "benchmarks"):  # run as a plain script from a checkout
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from results_path import results_path  # noqa: E402

from training.zoo_eval_layout import ENDED, EVALS, RUN_ID_FILE, saved_checkpoints  # noqa: E402
from training.zoo_eval_record import Ledger  # noqa: E402
from training.zoo_evaluator import member_and_seed  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results"
FIGSIZE, DPI = (7.0, 6.0), 100  # the figure is 700 x 600 px
LINESTYLES = ("-", "--", ":", "-.")
Entry = dict[str, Any]


def portable(path: Path | str) -> str:
    """A path as the repository names it: from its ``data/`` (or the repo root) on."""
    p = Path(path).resolve()
    if p.is_relative_to(ROOT):
        return str(p.relative_to(ROOT))
    return str(Path(*p.parts[p.parts.index("data") :])) if "data" in p.parts else str(p)


def _finite(x: Any) -> float | None:
    return float(x) if isinstance(x, int | float) and math.isfinite(x) else None


def step_entry(record: Entry) -> Entry:
    """One ledger line as figures: each part's numbers where they were measured, else None;
    a failure's message under ``error``."""
    m = {k: v for k, v in (record.get("metrics") or {}).items() if _finite(v) is not None}
    openloop = None
    if "openloop_r_img" in m:
        openloop = {
            "r_img": m["openloop_r_img"],
            "ci95": [m["openloop_r_img_lo"], m["openloop_r_img_hi"]],
            "e_img": m.get("openloop_e_img"),
            "e_prop": m.get("openloop_e_prop"),
        }
    closedloop = None
    n = int(m.get("closedloop_episodes", 0))
    if "success_diagnose" in m and n > 0:
        has_r = "closedloop_r_img" in m
        closedloop = {
            "successes": round(m["success_diagnose"] * n),
            "n": n,
            "success": m["success_diagnose"],
            "wilson95": [m["success_lo"], m["success_hi"]],
            "r_img": m.get("closedloop_r_img"),
            "r_img_ci95": [m["closedloop_r_img_lo"], m["closedloop_r_img_hi"]] if has_r else None,
            "error_episodes": int(m.get("closedloop_errors", 0)),
            "success_control": m.get("success_control"),
        }
    return {
        "step": int(record["step"]),
        "status": record.get("status", "error"),
        "ran": list(record.get("ran") or []),
        "openloop": openloop,
        "closedloop": closedloop,
        "eval_cpu_s": _finite(record.get("cpu_s")),
        "eval_wall_s": _finite(record.get("wall_s")),
        "error": record.get("error"),
    }


def eval_settings(evals: Path) -> Entry:
    """The evaluator's params as its MLflow run holds them (the default store,
    ``RUN/evals/mlflow.db``, read-only); empty where there is none."""
    db, id_file = evals / "mlflow.db", evals / RUN_ID_FILE
    if not db.is_file() or not id_file.is_file():
        return {}
    with sqlite3.connect(f"file:{db}?mode=ro", uri=True) as con:
        rows = con.execute(
            "select key, value from params where run_uuid = ?", (id_file.read_text().strip(),)
        ).fetchall()
    p = dict(rows)
    ints = ("eval_every", "closed_loop_every", "closed_loop_episodes", "frames_count")
    out: Entry = {k: int(p[k]) for k in ints if k in p}
    if "frames" in p:
        out["frames"] = portable(p["frames"])
        info = Path(p["frames"]) / "meta" / "info.json"
        if info.is_file():
            out["frames_episodes"] = json.loads(info.read_text()).get("total_episodes")
    return out


def train_record(run: Path) -> Entry:
    """What the run folder says of its training: the config's steps, batch and seed, the last
    saved step, and the sessions' wall and CPU seconds (``zoo_sessions.jsonl``, written as
    each ``zoo train`` ends)."""
    saved = saved_checkpoints(run)
    out: Entry = {"last_saved_step": max(saved) if saved else None}
    if saved:
        cfg = saved[max(saved)] / "pretrained_model" / "train_config.json"
        if cfg.is_file():
            c = json.loads(cfg.read_text())
            out.update({k: c.get(k) for k in ("steps", "batch_size", "seed", "save_freq")})
    log = run / "zoo_sessions.jsonl"
    sessions = [json.loads(s) for s in log.read_text().splitlines() if s] if log.is_file() else []
    if sessions:
        out["sessions"] = len(sessions)
        out["wall_s"] = round(sum(s["seconds"] for s in sessions), 1)
        out["cpu_s"] = round(sum(s.get("train_cpu_s") or 0.0 for s in sessions), 1)
        out["machines"] = sorted({s["cpu"] for s in sessions})
        out["threads"] = sorted({s["threads"] for s in sessions})
    out["ended"] = (run / EVALS / ENDED).exists()
    return out


def read_run(run: Path) -> tuple[str, Entry]:
    """``member@seedS`` and its entry: the evaluated steps in order (a step recorded again, as
    an incomplete checkpoint later whole, keeps its last line)."""
    member, seed = member_and_seed(run)
    ledger = Ledger(run / EVALS)
    by_step = {int(r["step"]): r for r in ledger.records()}
    if not by_step:
        raise SystemExit(f"--run {run}: {ledger.path} holds no evaluated step yet")
    settings = eval_settings(run / EVALS)
    steps = [step_entry(by_step[s]) for s in sorted(by_step)]
    return f"{member}@seed{seed}", {
        "member": member,
        "seed": seed,
        "run_dir": portable(run),
        "settings": settings,
        "train": train_record(run),
        "steps": steps,
        "evaluated": sum(s["openloop"] is not None for s in steps),
        "closed_loop_steps": sum(s["closedloop"] is not None for s in steps),
    }


def shipped_final(member: str, benchmark: str, results: Path = RESULTS) -> tuple[str, Entry]:
    """The shipped checkpoint's final figures: its open-loop R_img on the held-out frames
    (``reliance_<benchmark>.json``) and its card's diagnose cell (``zoo_<benchmark>.json``)."""
    from pipeline.results.aggregate import wilson

    rel = json.loads((results / f"reliance_{benchmark}.json").read_text())
    cards = json.loads((results / f"zoo_{benchmark}.json").read_text())["members"]
    if member not in rel["members"] or member not in cards:
        raise SystemExit(
            f"--final {member}: not in both reliance_{benchmark}.json and zoo_{benchmark}.json "
            f"of {results} (members in both: {sorted(set(rel['members']) & set(cards))})"
        )
    card = cards[member]
    r, t = rel["members"][member], card["train"]
    diag = [x for x in card["tasks"] if x["cell"] == "diagnose"]
    k, n = sum(x["successes"] for x in diag), sum(x["n"] for x in diag)
    eff = card["diagnose_effects"]
    return f"{member}@seed{t['seed']}", {
        "member": member,
        "seed": t["seed"],
        "step": t["steps"],
        "openloop": {"r_img": r["r_img"], "ci95": r["ci95"], "e_img": r["e_img"],
                     "e_prop": r["e_prop"], "frames": rel["frames"]},
        "closedloop": {"successes": k, "n": n, "success": k / n, "wilson95": list(wilson(k, n)),
                       "r_img": eff["r_img"], "r_img_ci95": eff.get("r_img_ci95"),
                       "episodes_per_task": card["eval"]["episodes_per_task"]},
        "sources": [f"benchmarks/results/reliance_{benchmark}.json",
                    f"benchmarks/results/zoo_{benchmark}.json"],
    }  # fmt: skip


def collect(
    runs: list[Path], finals: list[str], benchmark: str, command: str, kept: Entry | None = None
) -> Entry:
    """The results file's content; ``kept``: a results file whose other runs and finals stay
    (``--merge``), each run with the machine and command it was gathered with."""
    from workers.hardware import machine_record

    here = machine_record()
    new = {
        key: {**entry, "machine": here, "command": command} for key, entry in map(read_run, runs)
    }
    old = {
        key: {"machine": kept.get("machine"), "command": kept.get("command"), **entry}
        for key, entry in (kept or {}).get("runs", {}).items()
        if key not in new
    }
    return {
        "benchmark": benchmark,
        "machine": here,
        "date": date.today().isoformat(),
        "command": command,
        "runs": {**old, **new},
        "finals": {
            **(kept or {}).get("finals", {}),
            **dict(shipped_final(m, benchmark) for m in finals),
        },
    }


def draw(data: Entry, path: Path) -> None:
    """Two panels over the training step: open-loop R_img with its 95% band, and closed-loop
    success with Wilson error bars; a colour per member, a line style per seed; a shipped
    final checkpoint as a hollow diamond; a failed step as a dotted grey line."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=FIGSIZE, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, sharex=True)
    runs, finals = data["runs"], data.get("finals", {})
    members = sorted({e["member"] for e in [*runs.values(), *finals.values()]})
    seeds = sorted({e["seed"] for e in runs.values()}, key=lambda s: (s is None, s))
    colour = {m: f"C{i % 10}" for i, m in enumerate(members)}
    span = max([s["step"] for e in runs.values() for s in e["steps"]], default=1)
    for i, e in enumerate(runs.values()):
        c, ls = colour[e["member"]], LINESTYLES[seeds.index(e["seed"]) % len(LINESTYLES)]
        label = f"{e['member']} seed {e['seed']}"
        ol = [s for s in e["steps"] if s["openloop"]]
        x = [s["step"] for s in ol]
        top.plot(x, [s["openloop"]["r_img"] for s in ol], ls, color=c, marker="o", label=label)
        top.fill_between(x, *zip(*(s["openloop"]["ci95"] for s in ol), strict=True), color=c,
                         alpha=0.15, linewidth=0)  # fmt: skip
        cl = [s for s in e["steps"] if s["closedloop"]]
        dodge = span * 0.008 * (i - (len(runs) - 1) / 2)  # bars of runs at one step side by side
        y = [s["closedloop"]["success"] for s in cl]
        err = [[v - s["closedloop"]["wilson95"][0] for v, s in zip(y, cl, strict=True)],
               [s["closedloop"]["wilson95"][1] - v for v, s in zip(y, cl, strict=True)]]  # fmt: skip
        bottom.errorbar([s["step"] + dodge for s in cl], y, yerr=err, fmt="o", linestyle=ls,
                        color=c, capsize=3, label=label)  # fmt: skip
        for s in e["steps"]:
            if s["error"]:
                for ax in (top, bottom):
                    ax.axvline(s["step"], color="0.6", linestyle=":", linewidth=1)
    for e in finals.values():
        c, label = colour[e["member"]], f"{e['member']} seed {e['seed']}, shipped (final)"
        for ax, part, ci in ((top, "openloop", "ci95"), (bottom, "closedloop", "wilson95")):
            v, (lo, hi) = e[part]["success" if part == "closedloop" else "r_img"], e[part][ci]
            ax.errorbar([e["step"]], [v], yerr=[[v - lo], [hi - v]], fmt="D", color=c,
                        markerfacecolor="none", capsize=3, label=label)  # fmt: skip
    top.set_ylabel("open-loop R_img (95% CI)")
    bottom.set_ylabel("closed-loop success (Wilson 95%)")
    bottom.set_xlabel("training step")
    bottom.set_xlim(left=0)
    for ax in (top, bottom):
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
    top.legend(fontsize="small", loc="best")
    top.set_title(f"{data['benchmark']}: reliance on vision and success over training")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--run", type=Path, action="append", required=True, help="a zoo run folder")
    ap.add_argument("--final", action="append", default=[], metavar="MEMBER",
                    help="add the shipped MEMBER's final figures from the results files")  # fmt: skip
    ap.add_argument("--benchmark", default="metaworld")
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--figure", type=Path, default=None)
    ap.add_argument("--dry", action="store_true", help="write to a temporary folder")
    ap.add_argument(
        "--merge", action="store_true", help="keep the runs the results file holds under other keys"
    )
    args = ap.parse_args(argv)
    committed = RESULTS / f"zoo_training_{args.benchmark}.json"
    out = results_path(committed, args.out, "--dry" if args.dry else None)
    figure = args.figure or (
        out.with_suffix(".png")
        if args.dry and args.out is None
        else ROOT / "docs" / "img" / f"zoo_training_{args.benchmark}.png"
    )
    command = " ".join(
        ["python benchmarks/zoo_training.py", *(f"--run {portable(r)}" for r in args.run),
         *(f"--final {m}" for m in args.final)]
        + ([] if args.benchmark == "metaworld" else [f"--benchmark {args.benchmark}"])
    )  # fmt: skip
    kept = json.loads(out.read_text()) if args.merge and out.exists() else None
    data = collect(
        args.run, args.final, args.benchmark, command + (" --merge" if kept else ""), kept
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(data, indent=2, allow_nan=False) + "\n")
    draw(data, figure)
    print(f"wrote {out} and {figure}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
