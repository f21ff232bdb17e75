"""MkDocs hook: the fault table and the benchmark figures, rendered from benchmarks/results/*.json.

A page asks for a table with a line of its own, ``<!-- results: NAME -->``; the line is replaced
by the Markdown that ``RENDERERS[NAME]`` makes of ``benchmarks/results/NAME.json``. A name without
a renderer, or a missing file, raises: the build fails instead of showing an empty table.

A figure quoted in prose is a marker too, ``{{ NAME:PATH | OPS }}``, replaced by one value of
``benchmarks/results/NAME.json`` (see :func:`figure`), so the prose cannot drift from its file.
"""

from __future__ import annotations

import json
import math
import re
import statistics
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from mkdocs.exceptions import PluginError

if TYPE_CHECKING:
    from mkdocs.config.defaults import MkDocsConfig
    from mkdocs.structure.files import Files
    from mkdocs.structure.pages import Page

RESULTS = Path(__file__).resolve().parents[2] / "benchmarks" / "results"
MARKER = re.compile(r"^<!--\s*results:\s*(.*?)\s*-->[ \t]*$", re.MULTILINE)
FIGURE = re.compile(r"\{\{\s*(\w+):([^|{}]+?)\s*(?:\|\s*([^{}]*?)\s*)?\}\}")

Data = dict[str, Any]


# -- formatting ---------------------------------------------------------------------------------


def num(x: Any, sig: int = 3) -> str:
    """A measured number for a table: ints with thousands separators, floats to ``sig`` figures."""
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return f"{x:,}"
    if isinstance(x, float):
        if x.is_integer() and abs(x) < 1e6:
            return f"{int(x):,}"
        if abs(x) >= 10 ** (sig - 1):
            return f"{x:,.0f}"
        return f"{x:#.{sig}g}".rstrip(".")
    if x is None:
        return "-"
    return str(x)


def pct(x: float) -> str:
    """A fraction as a percentage (one decimal below 1%)."""
    return f"{100 * x:.0f}%" if x == 0 or abs(x) >= 0.01 else f"{100 * x:.1f}%"


def table(header: Iterable[str], rows: Iterable[Iterable[Any]]) -> str:
    """A Markdown table; cells are strings or numbers (formatted by :func:`num`)."""
    cells = [[c if isinstance(c, str) else num(c) for c in row] for row in rows]
    head = list(header)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in cells]
    return "\n".join(lines)


def machine(data: Mapping[str, Any]) -> str:
    """The machine line a result records, if any; a record without the CPU's model says so."""
    m = data.get("machine")
    if isinstance(m, Mapping):
        spelled = {
            "cpu_model": "{}",
            "cpu_capability": "torch dispatching {}",
            "device_name": "{}",
            "cpus": "{} CPUs",
            "threads": "{} threads",
            "python": "Python {}",
            "torch": "torch {}",
            "cuda": "CUDA {}",
        }
        line = ", ".join(f.format(m[k]) for k, f in spelled.items() if m.get(k) is not None)
        return line if "cpu_model" in m else f"{line} (CPU model not recorded)"
    return f"{m} (CPU model not recorded)" if m else ""


def source(name: str, data: Mapping[str, Any], *extra: str) -> str:
    """The caption under a table: which file, on what machine, when."""
    bits = [f"`benchmarks/results/{name}.json`"]
    if m := machine(data):
        bits.append(f"machine: {m}")
    for key in ("date", "generated_at"):
        if key in data:
            bits.append(f"{key.replace('_', ' ')}: {data[key]}")
    bits.extend(e for e in extra if e)
    return "*" + "; ".join(bits) + "*"


def block(*parts: str) -> str:
    """Paragraphs and tables separated by blank lines."""
    return "\n\n" + "\n\n".join(p for p in parts if p) + "\n\n"


def key_values(rows: Iterable[tuple[str, Any]]) -> str:
    """A two-column table of named figures."""
    return table(["what", "figure"], rows)


def reliance_metaworld(d: Data) -> str:
    """reliance_metaworld.json (a copy of ``idr-eval reliance``'s reliance.json): open-loop R_img
    per member on the shared held-out frames, by fifth of progress and by gripper phase, and one
    member under each intervention strategy."""

    def cell(f: Mapping[str, Any]) -> str:
        if not f["frames"]:
            return "–"
        return f"{f['r_img']:.2f} [{f['ci95'][0]:.2f}, {f['ci95'][1]:.2f}]"

    members = d["members"]
    overall = table(
        ["member", "R_img (95% CI)", "E_img", "E_prop", "frames", "episodes"],
        [
            [name, cell(m), num(m["e_img"]), num(m["e_prop"]), str(m["frames"]), str(m["episodes"])]
            for name, m in members.items()
        ],
    )
    fifths = table(
        ["member", *(f"{f / 5:.1f}-{(f + 1) / 5:.1f}" for f in range(5))],
        [[name, *(cell(f) for f in m["by_fifth"])] for name, m in members.items()],
    )
    phases = table(
        ["member", "open", "closed", "released", "frames without a grasp"],
        [
            [name, *(f"{cell(m['by_phase'][p])} (n={m['by_phase'][p]['frames']})"
                     for p in ("open", "closed", "released")), str(m["no_gripper_frames"])]
            for name, m in members.items()
        ],
    )  # fmt: skip
    parts = [overall, "By fifth of progress through the episode:", fifths,
             "By gripper phase (the demonstration's own gripper command):", phases]  # fmt: skip
    if "strategies" in d:
        s = d["strategies"]
        parts += [
            f"{s['member']} under each intervention strategy (do(V) and do(S) alike):",
            table(
                ["strategy", "R_img (95% CI)"], [[k, cell(v)] for k, v in s["by_strategy"].items()]
            ),
        ]
    frames = d["frames"]
    wall = f", {d['wall_seconds'] / 60:.0f} minutes" if "wall_seconds" in d else ""
    note = (
        f"{frames['n']} frames of {frames['episodes']} held-out episodes (`{frames['source']}`), "
        f"do(S) {d['intervention']['state_space']}{wall}"
    )
    return block(*parts, source("reliance_metaworld", d, note))


def _r_img(part: Mapping[str, Any] | None, ci: str = "ci95") -> str:
    if not part or part.get("r_img") is None:
        return "–"
    lo, hi = part[ci] if part.get(ci) else (None, None)
    return num(part["r_img"]) + (f" [{num(lo)}, {num(hi)}]" if lo is not None else "")


def _success(part: Mapping[str, Any] | None) -> str:
    if not part:
        return "–"
    lo, hi = part["wilson95"]
    return (
        f"{part['successes']}/{part['n']}: {100 * part['success']:.0f}% "
        f"[{100 * lo:.0f}, {100 * hi:.0f}]"
    )


def _training_run(r: Mapping[str, Any]) -> list[str]:
    """One member@seed of zoo_training_*.json: what ran, then a row per evaluated step; a part
    that ran without figures reads ``error`` (its message under the table)."""
    s, t = r["settings"], r["train"]
    head = f"**{r['member']}, seed {r['seed']}** (`{r['run_dir']}`): "
    if t.get("steps"):
        head += f"{t['steps']:,} steps planned at batch {t.get('batch_size')}, "
    head += f"checkpoints saved through step {num(t.get('last_saved_step'))}"
    head += "" if t.get("ended") else " (training under way)"
    if t.get("wall_s") is not None:
        head += (
            f"; training {t['wall_s'] / 60:.0f} min wall, {num(t['cpu_s'])} CPU s on "
            f"{', '.join(t['machines'])} ({'/'.join(map(str, t['threads']))} threads)"
        )
    if s:
        closed = (s.get("eval_every") or 0) * (s.get("closed_loop_every") or 0)
        head += (
            f". Evaluated every {s.get('eval_every')} steps: open loop on "
            f"{num(s.get('frames_count'))} frames of {num(s.get('frames_episodes'))} held-out "
            f"episodes (`{s.get('frames')}`), the closed-loop diagnose cell every {closed} steps "
            f"with {s.get('closed_loop_episodes')} episodes per task"
        )
    head += f"; closed loop at {r['closed_loop_steps']} of {len(r['steps'])} evaluated steps"
    head += f" (gathered on {m}, where its run folder was)." if (m := machine(r)) else "."

    def cell(step: Mapping[str, Any], part: str, text: str) -> str:
        return "error" if text == "–" and part in step["ran"] else text

    rows = [
        [
            f"{st['step']:,}",
            cell(st, "openloop", _r_img(st["openloop"])),
            cell(st, "closedloop", _success(st["closedloop"])),
            cell(st, "closedloop", _r_img(st["closedloop"], "r_img_ci95")),
            num(st["eval_cpu_s"]),
        ]
        for st in r["steps"]
    ]
    body = table(
        ["step", "open-loop R_img [95% CI]", "closed-loop success k/n [Wilson 95%]",
         "closed-loop R_img [95% CI]", "evaluator CPU s"],
        rows,
    )  # fmt: skip
    errors = [f"- step {st['step']:,} ({st['status']}): {st['error']}" for st in r["steps"]
              if st.get("error")]  # fmt: skip
    return [head, body, "\n".join(errors)]


def zoo_training_metaworld(d: Data) -> str:
    """zoo_training_metaworld.json (benchmarks/zoo_training.py): per member@seed, every
    evaluated checkpoint's open-loop R_img and, where the closed loop ran, its success and R_img;
    the shipped final checkpoints measured on the same frames beside them."""
    parts = [p for r in d["runs"].values() for p in _training_run(r)]
    if d.get("finals"):
        rows = [
            [key, f"{f['step']:,}", _r_img(f["openloop"]), _success(f["closedloop"]),
             _r_img(f["closedloop"], "r_img_ci95"),
             f"{f['openloop']['frames']['n']:,} frames of `{f['openloop']['frames']['source']}`; "
             f"{f['closedloop']['episodes_per_task']} "
             f"episodes per task ({', '.join(f'`{s}`' for s in f['sources'])})"]
            for key, f in d["finals"].items()
        ]  # fmt: skip
        parts += [
            "The shipped checkpoints' final figures (the closed loop from their card's diagnose "
            "cell):",
            table(["member@seed", "step", "open-loop R_img [95% CI]", "closed-loop success",
                   "closed-loop R_img [95% CI]", "measured on"], rows),
        ]  # fmt: skip
    note = (
        "the evaluator ran beside training, on the machine that gathered its run (each run names "
        f"it; else the one named here); its CPU seconds are its own and its children's; command: "
        f"`{d['command']}`"
    )
    return block(*parts, source("zoo_training_metaworld", d, note))


# -- one renderer per results file --------------------------------------------------------------

_COMMON = ("lost", "duplicated", "unexpected", "unreadable_files", "temp_files_left")
_COMMON += ("orphan_step_files",)


def faults(d: Data) -> str:
    """faults.json: every injected fault, what is guaranteed and what the test measured."""
    totals = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in d["totals"].items())
    head = (
        f"**{len(d['faults'])} faults** injected by `python benchmarks/fault_report.py` "
        f"(pytest exit code {d['pytest_exit_code']}, {num(d['wall_seconds'])} s). "
        f"Totals over every run: **{totals}**."
    )
    rows = []
    for f in d["faults"]:
        out = f["outcome"]
        shown = {k: v for k, v in out.items() if not (k in _COMMON and v == 0)}
        measured = ", ".join(f"{k.replace('_', ' ')}: {num(v)}" for k, v in shown.items())
        test = f["test"].removeprefix("tests/pipeline/")
        rows.append([f["fault"], f["injected"], f["guaranteed"], measured, f"`{test}`"])
    body = table(["fault", "how injected", "what is guaranteed", "measured", "test"], rows)
    return block(head, body, source("faults", d, f"command: `python {d['command']}`"))


def default_run(d: Data) -> str:
    """default_run.json: the run's pace, success per cell and task, where the time goes."""
    run = d["run"]
    pace = key_values(
        [
            ("episodes", run["episodes"]),
            ("workers", run["workers"]),
            ("wall time (min)", run["wall_minutes"]),
            ("episodes per minute", run["episodes_per_minute"]),
            (
                "mean episode (s) / env steps",
                f"{num(run['episode_seconds_mean'])} / {num(run['env_steps_mean'])}",
            ),
        ]
    )
    success: dict[str, dict[str, float]] = {}
    for key, value in run["success_by_cell_task"].items():
        cell, _, task = key.partition("/")
        success.setdefault(task, {})[cell] = value
    seen = {c: None for by_cell in success.values() for c in by_cell}
    cells = [c for c in d.get("per_cell", {}) if c in seen] + [
        c for c in seen if c not in d.get("per_cell", {})
    ]
    succ = table(
        ["task", *cells],
        [[task, *(pct(by[c]) if c in by else "-" for c in cells)] for task, by in success.items()],
    )
    share = table(
        ["part of the episode time", "share", "ms per call"],
        [[k.replace("_", " "), pct(v), num(d["ms_per_call"].get(k))] for k, v in d["share"].items()]
        + [["Parquet + MLflow logging", pct(d["logging_share_of_episode_time"]), "-"]],
    )
    paired = table(
        [
            "cell",
            f"Δ vs {run.get('reference', 'the reference')} (pp, bootstrap 95% CI)",
            "p (McNemar)",
            "pairs",
        ],
        [
            [
                p["cell_id"],
                f"{100 * p['diff']:+.1f} [{100 * p['ci_low']:+.1f}, {100 * p['ci_high']:+.1f}]",
                num(p["p_value"]),
                p["n_pairs"],
            ]
            for p in run.get("paired", [])
        ],
    )
    note = f"{d['config']}, `{run['run_dir']}`; time shares from {d['episodes']} episodes: "
    parts = [pace, succ, paired, share] if run.get("paired") else [pace, succ, share]
    return block(*parts, source("default_run", d, note + d["note"]))


def engine(d: Data) -> str:
    """engine.json: scheduling overhead, scaling, store writes, aggregation."""
    s, w = d["scheduling_overhead"], d["scaling_1_vs_2_workers"]
    st, ag = d["store_write"], d["aggregate_steps"]
    rows = [
        ("Ray scheduling overhead per episode vs inline (ms)", s["ray_overhead_ms_per_episode"]),
        ("2 Ray workers vs 1, CPU-bound fake episodes (throughput)", f"{num(w['speedup'])}x"),
        ("store write rate (rows/s)", st["rows_per_s"]),
        (f"aggregate a {num(ag['rows'])}-row steps table (s)", ag["seconds"]),
    ]
    return block(key_values(rows), source("engine", d))


def tabletop_env(d: Data) -> str:
    """tabletop_env.json: ms per step by task, image size, cameras and look."""
    rows = [
        [r["task"], r["image_size"], r["cameras"], r["look"], r["ms_per_step"], r["steps_per_s"]]
        for r in d["rows"]
    ]
    body = table(["task", "px", "cameras", "look", "ms per step", "steps/s"], rows)
    return block(body, source("tabletop_env", d, f"render backend {d['backend']}"))


def libero_env(d: Data) -> str:
    """libero_env.json: per-step cost by cameras and size; eager vs lazy rendering."""
    by_size = table(
        ["cameras", "px", "ms per step", "build + first reset (s)", "reset (s)"],
        [
            [
                ", ".join(r["cameras"]) or "none",
                r["image_size"],
                r["ms_per_step"],
                r["build_and_first_reset_s"],
                r["reset_s"],
            ]
            for r in d["results"]
        ],
    )
    lazy = table(
        ["rendering", "images read", "px", "ms per step", "reset (s)", "pixels equal eager"],
        [
            [
                "lazy" if p["lazy_render"] else "eager",
                f"every {p['read_every']} step(s)",
                p["image_size"],
                p["ms_per_step"],
                p["reset_s"],
                p["pixels_equal_eager"],
            ]
            for p in d["patterns"]
        ],
    )
    return block(by_size, lazy, source("libero_env", d, f"task {d['task']}"))


def libero_pro_step(d: Data) -> str:
    """libero_pro_step.json: LIBERO-PRO in its env server against our LIBERO, same task."""
    by_env: dict[str, dict[int, Mapping[str, Any]]] = {}
    for r in d["results"]:
        by_env.setdefault(r["env"], {})[r["read_every"]] = r
    rows = [
        [env, x[1]["ms_per_step"], x[8]["ms_per_step"], x[8]["reset_s"]]
        for env, x in by_env.items()
    ]
    body = table(
        ["env", "ms per step, images read every step", "every 8th step", "reset (s)"], rows
    )
    what = (
        f"task index {d['task_index']}, {', '.join(d['cameras'])} at {d['image_size']} px, "
        f"{d['steps']} steps"
    )
    return block(body, source("libero_pro_step", d, what))


def env_server(d: Data) -> str:
    """env_server.json: the same env in-process vs in an env server."""
    rows = [
        [case.replace("_", " "), v["in_process_ms"], v["server_ms"], v["overhead_ms"]]
        for case, v in d["per_step"].items()
    ]
    body = table(["per step", "in-process ms", "env server ms", "difference ms"], rows)
    same = "identical states and pixels" if d["identical"] else "states or pixels differ"
    return block(body, source("env_server", d, same, f"render backend {d['render_backend']}"))


def calvin_env(d: Data) -> str:
    """calvin_env.json: CALVIN in its env server, by renderer."""
    rows = [
        [
            name,
            r["open_loop_ms_per_step"],
            r["rendered_ms_per_step"],
            r["rendered_steps_per_s_per_core"],
            r["new_sequence_reset_s"],
        ]
        for name, r in d["renderers"].items()
    ]
    header = [
        "renderer",
        "physics + oracle ms/step",
        "rendered ms/step",
        "rendered steps/s",
        "new sequence (s)",
    ]
    return block(table(header, rows), source("calvin_env", d, d["what"]))


def policy_service(d: Data) -> str:
    """policy_service.json: round trip, batching, overlap and the one-GPU model."""
    rt = d["round_trip"]
    trip = key_values(
        [
            ("round trip per inference, in-process (ms)", rt["in_process_ms"]),
            ("round trip per inference, policy actor (ms)", rt["policy_actor_ms"]),
            ("Ray's bare round trip (ms)", rt["ray_round_trip_ms"]),
        ]
    )
    names = list(d["batching"])
    ns = [r["n"] for r in d["batching"][names[0]]]
    batching = table(
        ["N requests", *(f"{b}: one forward / N forwards" for b in names)],
        [[n, *(num(d["batching"][b][i]["ratio"]) + "x" for b in names)] for i, n in enumerate(ns)],
    )
    o = d["overlap"]
    overlap = table(
        ["policy", "env steps/s", "episodes/min"],
        [[k, v["env_steps_per_s"], v["episodes_per_min"]] for k, v in o.items() if k != "model"]
        + [
            ["model: in-actor predicted", o["model"]["in_actor_predicted_steps_per_s"], "-"],
            ["model: shared ceiling", o["model"]["shared_ceiling_steps_per_s"], "-"],
        ],
    )
    g = d["gpu_node_model"]
    gpu = table(
        [
            "simulator cores",
            "simulator-bound obs/s",
            "compute-bound obs/s (IDR)",
            "lerobot eager pi0.5 obs/s",
        ],
        [
            [
                r["sim_cores"],
                r["sim_bound_obs_per_s"],
                r["predicted_obs_per_s_compute_bound"],
                r["predicted_obs_per_s_lerobot_eager"],
            ]
            for r in g["rows"]
        ],
    )
    assumptions = "; ".join(f"{k.replace('_', ' ')}: {v}" for k, v in g["assumptions"].items())
    return block(
        trip,
        batching,
        overlap,
        gpu,
        f"Model assumptions: {assumptions}.",
        vla_eval(g.get("vla_eval")),
        source("policy_service", d),
    )


def vla_eval(v: Mapping[str, Any] | None) -> str:
    """The public reference the one-GPU model is set against (vla-eval's harness, no IDR)."""
    if not v:
        return ""
    shards = " / ".join(num(x) for x in v["obs_per_s_16_32_shards"])
    return (
        f"Reference, vla-eval's harness without IDR: {shards} obs/s on 16 / 32 shards, "
        f"{num(v['ceiling_50_shards'])} obs/s at saturation (50 shards)."
    )


def remote_backbone(d: Data) -> str:
    """remote_backbone.json: an IDR inference in-process vs over websockets."""
    p = d["per_inference"]
    rows = [(k.replace("_ms", "").replace("_", " "), v) for k, v in p.items()]
    return block(table(["IDR inference", "ms"], rows), source("remote_backbone", d, d["what"]))


def report_scale(d: Data) -> str:
    """report_scale.json: reading a 100,000-episode run dir before and after compaction."""
    r = d["run_dir"]
    rows = []
    for what in ("key_scan", "report", "compare"):
        u, c = d["uncompacted"][what], d["compacted"][what]
        s = "scan_seconds" if what == "key_scan" else "seconds"
        rows.append([what.replace("_", " "), u[s], u["peak_mb"], c[s], c["peak_mb"]])
    rows.append(["compaction", d["compaction"]["seconds"], d["compaction"]["peak_mb"], "-", "-"])
    body = table(["", "uncompacted s", "peak MB", "compacted s", "peak MB"], rows)
    what = (
        f"{num(r['episodes'])} episodes, {num(r['step_rows'])} step rows, {num(r['files'])} files"
    )
    return block(body, source("report_scale", d, what))


def tracking_scale(d: Data) -> str:
    """tracking_scale.json: MLflow logging of a large grid."""
    rows = [
        ("grid", f"{d['cells']} cells x {d['tasks']} tasks, {num(d['episodes'])} episodes"),
        ("store", d["store"]),
        ("open the store (s)", d["open_s"]),
        ("start: parent + child runs (s)", d["start_s"]),
        ("finish: metrics, tables, runs ended (s)", d["finish_s"]),
        ("of which aggregation (s)", d["finish_of_which_aggregation_s"]),
        ("metrics per child", f"{d['metrics_per_child_min']}-{d['metrics_per_child_max']}"),
    ]
    return block(key_values(rows), source("tracking_scale", d))


def cluster(d: Data) -> str:
    """cluster.json: a real two-node Ray cluster on one machine."""
    o, t = d["overhead"], d["throughput"]
    rows = [
        (
            "episodes/s, one node vs two",
            f"{num(t['one_node_episodes_per_s'])} vs "
            f"{num(t['two_nodes_episodes_per_s'])} ({num(t['speedup'])}x)",
        ),
        (
            "ms per episode: inline / local Ray",
            f"{num(o['inline_ms_per_episode'])} / {num(o['local_ray_ms_per_episode'])}",
        ),
        (
            "ms per episode on the cluster: actor on the driver's node / the other",
            f"{num(o['cluster_same_node_ms_per_episode'])} / "
            f"{num(o['cluster_other_node_ms_per_episode'])}",
        ),
        (
            "`ray start` of the head / of a second node (s)",
            f"{num(d['head_start_s'])} / {num(d['node_start_s'])}",
        ),
    ]
    return block(key_values(rows), source("cluster", d, d["cluster"]))


def slurm(d: Data) -> str:
    """slurm.json: the smoke under a real Slurm (2 slurmd) vs a local Ray; a requeue."""
    s, loc, r = d["slurm"], d["local_ray"], d["requeue"]
    rows = [
        (
            "to the first stored episode (s): sbatch / local `idr-eval run`",
            f"{num(s['sbatch_to_first_episode_s'])} / {num(loc['start_to_first_episode_s'])}",
        ),
        (
            "to the end (s): sbatch / local",
            f"{num(s['sbatch_to_end_s'])} / {num(loc['start_to_end_s'])} "
            f"({num(d['slurm_over_local_ratio'])}x, +{num(d['slurm_overhead_s'])} s)",
        ),
        ("of which Ray up on the allocation (s)", num(s["ray_up_s"])),
        ("Slurm's hold of a requeued job (s)", num(r["slurm_hold_s"])),
        ("requeue to the first resumed episode, hold released (s)", num(r["requeue_to_resume_s"])),
    ]
    note = f"Medians of {d['repeats']} runs each."
    return block(key_values(rows), note, source("slurm", d))


def perturbations(d: Data) -> str:
    """perturbations.json: reset and step cost under each perturbation."""

    def rows(cases: Mapping[str, Any]) -> list[list[Any]]:
        return [
            [k, v["reset_ms"], v["step_ms"], f"{num(v['step_ratio'])}x"] for k, v in cases.items()
        ]

    head = ["perturbation", "reset ms", "step ms", "step vs none"]
    lib = d["libero"]
    return block(
        f"Tabletop ({d['episodes']} episodes x {d['steps_per_episode']} steps, "
        f"{d['image_size']} px):",
        table(head, rows(d["cases"])),
        f"LIBERO, {lib['task']} ({lib['episodes']} episodes x {lib['steps_per_episode']} steps, "
        f"{lib['image_size']} px):",
        table(head, rows(lib["cases"])),
        source("perturbations", d),
    )


def plugin_latency(d: Data) -> str:
    """plugin_latency.json: the lerobot policy type idr per chunk, base vs IDR."""
    rows = [
        [
            name,
            f"{num(b['median_ms']['baseline'])} / {num(b['p90_ms']['baseline'])}",
            b["median_ms"]["diagnose"],
            b["median_ms"]["E"],
            f"{num(b['ratio_E_vs_baseline'])}x",
        ]
        for name, b in d["backbones"].items()
    ]
    head = ["base", "baseline ms (median / p90)", "diagnose ms", "E ms", "E / baseline"]
    skipped = "; ".join(f"{k}: skipped ({v})" for k, v in d.get("skipped", {}).items())
    return block(table(head, rows), skipped, source("plugin_latency", d, d["what"]))


def _passes(name: str, d: Data) -> str:
    rows = []
    for b, v in d["backbones"].items():
        if "median_ms" not in v:
            continue
        m = v["median_ms"]
        rows.append(
            [
                b,
                m["single"],
                m["batched_3pass"],
                m["sequential_3pass"],
                f"{num(v['ratio_batched_vs_single'])}x",
                f"{num(v['ratio_sequential_vs_single'])}x",
            ]
        )
    head = [
        "backbone",
        "one call ms",
        "3 passes, one 3B forward ms",
        "3 calls ms",
        "3B / one",
        "3 calls / one",
    ]
    return block(table(head, rows), source(name, d))


def idr_passes(d: Data) -> str:
    """idr_passes.json: IDR's three passes as one batched forward vs one call (CPU)."""
    return _passes("idr_passes", d)


def gpu_idr_passes(d: Data) -> str:
    """gpu_idr_passes.json: the same on a GPU (medians; the machine as recorded)."""
    return _passes("gpu_idr_passes", d)


def gpu_rendering(d: Data) -> str:
    """gpu_rendering.json: MuJoCo frames on a GPU's EGL."""
    rows = [
        [
            r["image_size"],
            r["cameras"],
            r["render_ms_per_frame_median"],
            r["render_ms_p90"],
            r["fps_frames"],
        ]
        for r in d["rows"]
    ]
    head = ["px", "cameras", "ms per frame (median)", "ms per step p90", "frames/s"]
    return block(
        table(head, rows), source("gpu_rendering", d, f"backend {d['backend']}", d["scene"])
    )


def tabletop_env_egl_h100(d: Data) -> str:
    """tabletop_env_egl_h100.json: the tabletop env on a GPU machine's EGL."""
    rows = [
        (
            "render per frame, agentview / wrist (ms)",
            f"{num(d['render_ms_per_frame_agentview'])} / {num(d['render_ms_per_frame_wrist'])}",
        ),
        ("step + both cameras (ms)", d["step_plus_2_renders_ms"]),
        ("reset (ms)", d["reset_ms"]),
        ("scene build (s)", d["scene_build_s"]),
    ]
    extra = (f"device: {d['device']}", f"backend {d['backend']}, {d['image_size']} px")
    return block(key_values(rows), source("tabletop_env_egl_h100", d, *extra))


def tiny_vla_alignment(d: Data) -> str:
    """tiny_vla_alignment.json: carry actions vs the expert's, by distance to the goal."""
    parts = [f"{d['task']}, seed {d['seed']}, {d['replan_steps']} actions per inference."]
    for ckpt, c in d["checkpoints"].items():
        outcomes = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in c["outcomes"].items())
        parts.append(f"`{ckpt}`, {c['episodes']} episodes: {outcomes}.")
        rows = []
        for b in c["by_distance"]:
            lo, hi = b["distance_cm"]
            span = f"> {num(lo)}" if hi is None else f"{num(lo)}-{num(hi)}"
            rows.append(
                [span, b["inferences"], b["cosine_mean"], b["policy_xy_norm"], b["expert_xy_norm"]]
            )
        head = [
            "distance to goal (cm)",
            "inferences",
            "cosine policy vs expert",
            "policy xy norm",
            "expert xy norm",
        ]
        parts.append(table(head, rows))
    return block(*parts, source("tiny_vla_alignment", d))


def shared_numerics(d: Data) -> str:
    """shared_numerics.json: forward cost per numerical path, run-to-run equality in closed loop."""
    parts = []
    for model, rows in d["forward_cost"].items():
        paths = [k.removesuffix("_ms") for k in rows[0] if k.endswith("_ms")]
        head = [
            "N requests",
            *(f"{p} (ms)" for p in paths),
            "rows=96 / dynamic",
            "rows=12 / dynamic",
        ]
        ratios = ("rows=96_vs_dynamic", "rows=12_vs_dynamic")
        body = [
            [r["n"], *(r[f"{p}_ms"] for p in paths), *(num(r[k]) + "x" for k in ratios)]
            for r in rows
        ]
        parts += [f"**{model}**, answering N IDR requests (3 rows each):", table(head, body)]
    loop = d.get("closed_loop")
    if loop:
        body = []
        for path, rec in loop.items():
            if not isinstance(rec, dict):  # episodes_per_task, run_dirs
                continue
            runs = rec["runs"]
            rates = "; ".join(
                f"{cell} {100 * v['success']:.0f}% [{100 * v['ci95'][0]:.0f}, {100 * v['ci95'][1]:.0f}]"
                for cell, v in sorted(runs[0]["success"].items())
            )
            body.append(
                [
                    path,
                    len(runs),
                    rec.get("episode_rows_differing", "-"),
                    " vs ".join(str(s) for s in rec.get("step_rows", [])) or "-",
                    " vs ".join(num(r["tau"][0], 6) if r["tau"] else "-" for r in runs),
                    num(statistics.mean(r["episodes_per_min"] for r in runs)),
                    rates,
                ]
            )
        head = ["path", "runs", "episode rows differing", "step rows", "calibrated τ",
                "episodes/min", "success (first run, Wilson 95%)"]  # fmt: skip
        parts += [
            f"The default preset at {loop['episodes_per_task']} episodes per task, twice per "
            "shared path (2 episode actors x 3 envs, one policy actor), once in-actor:",
            table(head, body),
        ]
    return block(*parts, source("shared_numerics", d))


def portable_numerics(d: Data) -> str:
    """portable_numerics.json: the portable mode run to run, against native, its cost, and the
    machines where the reference digest held or not."""
    w = d["wall_seconds"]
    here = d["measured_on"]
    figures = key_values(
        [
            ("slice", f"`{d['config']}` with {', '.join(f'`{o}`' for o in d['overrides'])}"),
            ("episodes", d["episodes"]),
            (
                "portable, run to run",
                "identical" if d["portable_run_to_run_identical"] else "differ",
            ),
            (
                "episodes equal native vs portable",
                f"{d['episodes_equal_native_vs_portable']} of {d['episodes']}",
            ),
            ("wall, portable (s)", f"{w['portable_1']}, {w['portable_2']}"),
            ("wall, native (s)", w["native"]),
            ("portable / native wall", num(d["portable_cost_ratio"]) + "x"),
            ("digest", f"`{d['digest'][:16]}`"),
        ]
    )
    machines = table(
        ["CPU model", "torch dispatches", "reference holds", "first difference", "date"],
        [
            [
                m["cpu_model"],
                m["cpu_capability"],
                "yes" if m["holds"] else "no",
                m.get("first_difference") or "–",
                m.get("date", ""),
            ]
            for m in d["machines"]
        ],
    )
    mach = f"{here['cpu_model']} ({here['cpu_capability']})"
    note = f"Note: {d['note']}." if d.get("note") else ""
    return block(figures, note, "Machines checked against the reference digest:", machines,
                 source("portable_numerics", d, f"measured on {mach}"))  # fmt: skip


def isa_spread(d: Data) -> str:
    """isa_spread.json: the default's headline under several instruction-set pins, against one
    run's sampling interval."""
    rows = []
    for name, r in d["pins"].items():
        h = r["headline"]
        pins = ", ".join(f"`{k}={v}`" for k, v in r["env"].items())
        pins = ", ".join(filter(None, [pins, *(f"`{o}`" for o in r["overrides"])])) or "none"
        rows.append(
            [
                name,
                pins,
                "; ".join(r["hardware_seen"]),
                f"{100 * h['diff']:+.1f} [{100 * h['ci_low']:+.1f}, {100 * h['ci_high']:+.1f}]",
                num(h["p_value"]),
                f"{h['only_cell']} / {h['only_baseline']}",
                f"{r['rows_identical_to_native']} of {r['episodes']}",
                r["step_rows"],
                r["wall_seconds"],
            ]
        )
    runs = table(
        [
            "pins",
            "set",
            "hardware class the actors recorded",
            "E − diagnose (pp, 95% CI)",
            "p (McNemar)",
            "only E / only diagnose",
            "rows = native",
            "step rows",
            "wall (s)",
        ],
        rows,
    )
    s = d["summary"]
    summary = key_values(
        [
            ("headline across pins (pp)", f"{100 * s['headline_min']:+.1f} to {100 * s['headline_max']:+.1f}"),
            ("spread across pins (pp)", f"{100 * s['headline_spread']:.1f}"),
            ("one run's 95% CI width (pp, mean)", f"{100 * s['ci_width_mean']:.1f}"),
            ("spread / CI width", num(s["spread_over_ci_width"])),
        ]
    )  # fmt: skip
    note = (
        f"`{d['config']}` with {', '.join(f'`{o}`' for o in d['overrides'])}, each pin a fresh run"
    )
    return block(runs, summary, source("isa_spread", d, note))


# per-core simulator rates the GPU supply prediction divides by (env steps/s, lazy rendering,
# OSMesa, this machine: docs/gpu-supply.md names their sources)
SIM_RATES_PER_CORE = {"LIBERO": 19.0, "CALVIN": 23.0}


def gpu_supply(d: Data) -> str:
    """gpu_supply.json: μ(B) per model and mode on a device, without and with IDR's triple, and
    what one device feeds at its best B (cores of each simulator at k = 10, vla-eval's 0.8 rule;
    through the shared service with its per-request overhead from serving.json)."""
    parts, fed = [], []
    overhead_ms = None
    serving_json = RESULTS / "serving.json"
    if serving_json.is_file():
        ours = json.loads(serving_json.read_text())["models"]["closed_form"]["ours"]["rows"]
        overhead_ms = next(r["overhead_ms"] for r in ours if r["clients"] == 1)
    for model, e in d["models"].items():
        if "skipped" in e:
            parts.append(f"**{model}**: skipped ({e['skipped']})")
            continue
        for mode in ("eager", "compiled"):
            m = e.get(mode)
            if m is None:
                parts.append(f"**{model}, {mode}**: not in this run")
                continue
            if "skipped" in m:
                parts.append(f"**{model}, {mode}**: skipped ({m['skipped']})")
                continue
            rows = []
            for b, r in m["per_batch"].items():
                base, idr = r["base"], r["idr"]
                if "ms" not in base or "ms" not in idr:
                    rows.append([int(b), base.get("skipped", "-"), "-", idr.get("skipped", "-"),
                                 "-", "-", "-"])  # fmt: skip
                    continue
                rows.append([int(b), base["ms"], base["mu_inf_per_s"], idr["ms"],
                             idr["mu_inf_per_s"], f"{num(r['idr_vs_base'])}x",
                             num(idr.get("peak_mem_gib"))])  # fmt: skip
            head = f"**{model}, {mode}** ({num(e['params_millions'])} M parameters"
            head += f", compiled in {num(m['compile_s'])} s)" if "compile_s" in m else ")"
            parts.append(head)
            parts.append(table(["B", "base ms", "μ base (inf/s)", "IDR ms", "μ_IDR (inf/s)",
                                "IDR / base", "peak GiB (IDR)"], rows))  # fmt: skip
            best = max(
                (r for r in m["per_batch"].values() if "mu_inf_per_s" in r["idr"]),
                key=lambda r: r["idr"]["mu_inf_per_s"],
                default=None,
            )
            if best is None:
                continue
            b, mu, t_ms = best["batch"], best["idr"]["mu_inf_per_s"], best["idr"]["ms"]
            cores = [num(0.8 * 10 * mu / rate) for rate in SIM_RATES_PER_CORE.values()]
            service = "-" if overhead_ms is None else num(b / ((t_ms + b * overhead_ms) / 1e3))
            fed.append([f"{model} {mode}", b, mu, 10 * mu, *cores, service])
    if fed:
        header = ["model", "B at max μ_IDR", "μ_IDR (inf/s)", "env steps/s at k = 10",
                  *(f"{n} cores fed" for n in SIM_RATES_PER_CORE),
                  "μ through the shared service (inf/s)"]  # fmt: skip
        parts.append(table(header, fed))
    note = f"{d['compile_mode'] or 'no'} compile mode, total {num(d['total_s'])} s"
    return block(*parts, source("gpu_supply", d, note))


def zoo_tabletop(d: Data) -> str:
    """zoo_tabletop.json: per member, its training record and its success per task and cell
    on the zoo preset, with Wilson intervals, its diagnose cell's effects and E vs diagnose."""
    return _zoo_card(d, "zoo_tabletop")


def zoo_metaworld(d: Data) -> str:
    """zoo_metaworld.json: the same card for the members trained on MetaWorld at 96 px."""
    return _zoo_card(d, "zoo_metaworld")


def zoo_tabletop_pos(d: Data) -> str:
    """zoo_tabletop_pos.json: the same card for lerobot's architectures trained on the tabletop
    state without its orientation dims (and evaluated on the same dims)."""
    return _zoo_card(d, "zoo_tabletop_pos")


def zoo_act_vision(d: Data) -> str:
    """zoo_act_vision.json: the tabletop_pos ACT on pick_color with and without images, 40
    episodes each (the card's layout)."""
    return _zoo_card(d, "zoo_act_vision")


def zoo_smolvla_vision(d: Data) -> str:
    """zoo_smolvla_vision.json: the tabletop_pos SmolVLA on pick_color with and without images,
    40 episodes each, diagnose only (the card's layout)."""
    return _zoo_card(d, "zoo_smolvla_vision")


def zoo_metaworld_vision(d: Data) -> str:
    """zoo_metaworld_vision.json: members trained on MetaWorld with black images at every step
    on two of their tasks (the card's layout)."""
    return _zoo_card(d, "zoo_metaworld_vision")


def paper_observations(d: Data) -> str:
    """paper_observations.json (a copy of the study's observations.json): per arch@env, R_img
    with its interval, E_img and E_prop, diagnose's success and E − diagnose; R_img against
    IDR's gain across the runs."""

    def pct(lo_hi: list[float]) -> str:
        return f"[{100 * lo_hi[0]:.0f}, {100 * lo_hi[1]:.0f}]"

    rows = []
    for r in d["runs"]:
        ok = r["success"]["diagnose"]
        g = r["gain_E"]
        rows.append(
            [r.get("label") or f"{r['arch']} @ {r['env']}", f"{r['r_img']:.2f} [{r['r_img_ci95'][0]:.2f}, "
             f"{r['r_img_ci95'][1]:.2f}]", num(r["e_img"]), num(r["e_prop"]),
             f"{100 * ok['rate']:.0f}% {pct(ok['ci95'])} (n={ok['n']})",
             f"{100 * g['diff']:+.1f} pp [{100 * g['ci95'][0]:+.1f}, {100 * g['ci95'][1]:+.1f}], "
             f"p = {g['mcnemar_p']:.2g}"]
        )  # fmt: skip
    c = d["rimg_vs_gain"]
    over = (
        f"{c['n']} members (one point per architecture @ environment, the mean over its "
        "training seeds)"
        if "members" in c
        else f"{c['n']} runs (each run a point: training seeds not pooled)"
    )
    note = (
        f"R_img against E − diagnose over {over}: Spearman ρ = {c['rho']:+.2f}, "
        f"permutation p = {c['p']:.2g} ({c['finding']})"
    )
    header = ["arch @ env", "R_img (95% CI)", "E_img", "E_prop", "diagnose success (95% CI)",
              "E − diagnose (95% CI, McNemar p)"]  # fmt: skip
    return block(
        table(header, rows),
        note,
        source("paper_observations", d),
    )


def _ci_pp(value: float, ci: list[float], signed: bool = True) -> str:
    f = "+.1f" if signed else ".1f"
    if not all(math.isfinite(x) for x in (value, *ci)):
        return "–"
    return f"{100 * value:{f}} [{100 * ci[0]:{f}}, {100 * ci[1]:{f}}]"


def _p_text(x: float | None) -> str:
    return "–" if x is None or not math.isfinite(x) else f"{x:.2g}"


PRIMARY_HEADER = ["member", "comparison", "seeds (each seed's Δ pp)", "Δ success pp [95% CI]",
                  "p (test)", "Holm p", "MDE pp"]  # fmt: skip


def confirmatory_metaworld(d: Data) -> str:
    """confirmatory_metaworld.json (benchmarks/confirmatory_study.py: the study's observations
    with the evidence of its declaration): the primary endpoints with Holm, each member pooled
    over its training seeds, each run's tau and success, the exploratory comparisons."""
    declared = "yes" if d["declared_before_data"] else "**no**"
    head = (
        f"*Confirmatory: `{d['study_file']}` committed at {d['commit'][:12]} "
        f"({d['committed_at']}), first episode {d['first_episode_at']}: declared before its "
        f"data: {declared}; endpoints hash {str(d['endpoints_hash'])[:12]}; "
        f"{d['wall_minutes']:.0f} minutes from first to last episode, summed over the "
        "sessions that ran the members.*"
    )
    if len(d.get("machines", [])) > 1:
        head += (
            "\n\n*Members ran on: "
            + "; ".join(machine({"machine": m}) for m in d["machines"])
            + ".*"
        )
    primary = []
    for r in d["comparisons"]["primary"]:
        per = ", ".join(f"s{k} {100 * v:+.0f}" for k, v in (r.get("per_seed") or {}).items())
        primary.append(
            [
                r["member"],
                f"{r['cell']} vs {r['reference']}",
                f"{r['seeds']} ({per})" if per else str(r["seeds"]) if r["ran"] else "not run",
                _ci_pp(r["diff"], r["ci95"]) if r["ran"] else "not run",
                f"{_p_text(r['p'])} ({r['test']})" if r["ran"] else "–",
                _p_text(r.get("p_holm")),
                "–" if not r["ran"] else f"≥ {r['mde_pp']:.0f}" if r["seeds"] > 1 else
                f"{r['mde_pp']:.0f}",
            ]
        )  # fmt: skip
    members = []
    for m in d["members"]:
        if "r_img" not in m:
            continue
        succ = m["success"]
        members.append(
            [
                m["member"],
                str(len(m["seeds"])),
                f"{m['r_img']['value']:.2f} [{m['r_img']['ci95'][0]:.2f}, "
                f"{m['r_img']['ci95'][1]:.2f}]",
                _ci_pp(succ[m["diagnose"]]["value"], succ[m["diagnose"]]["ci95"], signed=False),
                _ci_pp(succ["E"]["value"], succ["E"]["ci95"], signed=False),
            ]
        )
    runs = []
    for r in d["runs"]:
        label = f"{r['arch']}@{r['env']}:seed{r['seed']}"
        rec = d["run_records"].get(label, {})
        tau = (rec.get("tau") or {}).get("tau")
        fitted = (rec.get("tau") or {}).get("fitted_on", "-")
        s = r.get("success", {})
        runs.append(
            [label, f"{r['r_img']:.2f} [{r['r_img_ci95'][0]:.2f}, {r['r_img_ci95'][1]:.2f}]",
             "-" if tau is None else f"{tau:.2f} ({fitted})",
             *(f"{100 * s[c]['rate']:.0f}% (n={s[c]['n']})" if c in s else "-"
               for c in ("diagnose", "E", "random")),
             f"{rec.get('errors', '-')}"]
        )  # fmt: skip
    exploratory = [
        [
            r["member"],
            f"{r['cell']} vs {r['reference']}",
            str(r["seeds"]),
            _ci_pp(r["diff"], r["ci95"]),
            f"{_p_text(r['p'])} ({r['test']})",
        ]
        for r in d["comparisons"]["exploratory"]
    ]
    return block(
        head,
        "**Primary endpoints** (Holm over the declared six; one not run counts as p = 1)",
        table(PRIMARY_HEADER, primary),
        "**Members pooled over their training seeds** (two-level bootstrap 95% intervals)",
        table(["member", "seeds", "R_img", "diagnose success %", "E success %"], members),
        "**Each run** (τ fitted on its held-out episodes; success of each cell)",
        table(
            ["run", "R_img [95% CI]", "τ (fitted on)", "diagnose", "E", "random", "errors"], runs
        ),
        "**Exploratory** (not declared: uncorrected p, hypotheses for a later study)",
        table(["member", "comparison", "seeds", "Δ success pp [95% CI]", "p (test)"], exploratory),
        source("confirmatory_metaworld", d),
    )


def carried(c: dict | None) -> str:
    """How a checkpoint came from the machine that trained it (training/zoo_carry.py)."""
    if not c:
        return "as trained"
    return (
        f"{c['weights_dtype']}: max action change {c['max_abs_action_diff_in_std']:.1e} std "
        f"({c['frames']} frames)"
    )


def card_rimg(eff: dict) -> str:
    """A card's R_img: pooled over the diagnose cell's inferences with its interval, or, in an
    entry recorded without one, the ratio of the episodes' mean effects (the image-zeroed
    control's episodes included)."""
    if "r_img_ci95" not in eff:
        return f"{num(eff['r_img'])} (episode means, control included)"
    lo, hi = eff["r_img_ci95"]
    return f"{num(eff['r_img'])} [{num(lo)}, {num(hi)}]"


def _zoo_card(d: Data, name: str) -> str:
    train_rows, task_rows, effect_rows = [], [], []
    for member, m in d["members"].items():
        t, e = m["train"], m["eval"]
        train_rows.append(
            [
                member,
                t["policy_type"],
                "yes" if t["language"] else "no",
                f"{t['params']:,}",
                t["steps"],
                t["batch_size"],
                t["seed"],
                f"{t['train_seconds'] / 60:.0f} min",
                ", ".join(t["machines"])
                + f" ({'/'.join(map(str, t['threads']))} threads)"
                + "".join(f", {g}" for g in t.get("devices", []) if g != "cpu"),
                carried(t.get("carried")),
            ]
        )
        for r in m["tasks"]:
            lo, hi = r["ci95"]
            task_rows.append(
                [member, r["cell"], r["task"], f"{r['successes']}/{r['n']}",
                 f"{100 * r['success']:.0f} [{100 * lo:.0f}, {100 * hi:.0f}]"]
            )  # fmt: skip
        eff = m["diagnose_effects"]
        paired = "; ".join(
            f"{p['cell']} {100 * p['diff']:+.1f} pp [{100 * p['ci95'][0]:+.1f}, "
            f"{100 * p['ci95'][1]:+.1f}], p={p['mcnemar_p']:.2g} (n={p['n_pairs']})"
            for p in m["paired_vs_diagnose"]
        )
        effect_rows.append(
            [member, num(eff["e_img"]), num(eff["e_prop"]), card_rimg(eff), paired or "–",
             f"{e['episodes_per_task']} per task, {machine(e)}, {e['date']}"]
        )  # fmt: skip
    return block(
        table(
            ["member", "type", "instruction", "parameters", "steps", "batch", "seed",
             "training (wall)", "trained on", "weights carried"],
            train_rows,
        ),
        table(["member", "cell", "task", "successes", "success % [95% Wilson]"], task_rows),
        table(
            ["member", "E_img", "E_prop", "R_img (95% CI)", "E − diagnose (paired, 95% CI, McNemar)",
             "evaluated"],
            effect_rows,
        ),
        source(name, d),
    )  # fmt: skip


def breakdown_table(bds: dict[str, Data]) -> str:
    """Ours at B = 1 per transport (socket, ray): where the round trip goes."""
    transports = list(bds)
    lines = [
        ("round trip (ms)", "round_trip_ms"),
        ("client: observation and request (ms)", "client_ms"),
        ("transport: encoding, connection or Ray call, decoding (ms)", "transport_ms"),
        ("policy actor: handoff to and from the batching thread, batch wait (ms)",
         "actor_handoff_ms"),
        ("policy actor: the forward (ms)", "actor_forward_ms"),
        ("a bare Ray call to an actor busy for the forward's time (ms)", "ray_floor_busy_ms"),
    ]  # fmt: skip
    rows = [[label, *(num(bds[t][key]) for t in transports)] for label, key in lines]
    rows.append(
        ["round trip / that bare Ray call",
         *(f"{num(bds[t]['round_trip_ms'] / bds[t]['ray_floor_busy_ms'])}x" for t in transports)]
    )  # fmt: skip
    return table(["ours at B = 1", *(f"transport {t}" for t in transports)], rows)


def repeats_table(d: Data, reps: list[Data]) -> str:
    """The rows that later runs on the same machine repeated, beside the first run's: how far
    one run's row can be trusted."""
    rows = []
    for k, run in enumerate([d, *reps]):
        for model, e in run["models"].items():
            for path in ("ours", "ours_ray", "vla_eval"):
                for r in e.get(path, {}).get("rows", []):
                    if not any(
                        r["clients"] == q["clients"]
                        for rep in reps
                        for q in rep["models"].get(model, {}).get(path, {}).get("rows", [])
                    ):
                        continue  # not repeated
                    rows.append([k + 1, model, path, r["clients"], r["rtt_ms_median"],
                                 r["mu_per_s"], num(r["overhead_ms"])])  # fmt: skip
    return table(
        ["run", "model", "path", "B clients", "round trip median (ms)", "μ(B) (req/s)",
         "overhead per request (ms)"],
        rows,
    )  # fmt: skip


def serving(d: Data) -> str:
    """serving.json: one model through each serving path, B concurrent clients; ours' breakdown."""
    parts = []
    for model, e in d["models"].items():
        rows, skipped = [], []
        for path in ("in_process", "ours", "ours_ray", "vla_eval", "openpi", "ray_floor"):
            p = e.get(path)
            if p is None:
                continue
            if "skipped" in p:
                skipped.append(f"{path}: skipped ({p['skipped']})")
                continue
            for r in p["rows"]:
                overhead = "-" if path == "in_process" else num(r["overhead_ms"])
                rows.append(
                    [path, r["clients"], r["rtt_ms_median"], r["rtt_ms_p90"], r["mu_per_s"],
                     num(e["compute_ms"][str(r["clients"])]), overhead]
                )  # fmt: skip
        ratio_rows = []
        for other, per_b in e.get("ratios", {}).items():
            for b, v in per_b.items():
                o = v["overhead_ratio"]
                ratio_rows.append([other.removeprefix("ours_vs_"), int(b),
                                   "-" if o is None else f"{num(o)}x", f"{num(v['mu_ratio'])}x"])  # fmt: skip
        parts.append(f"**{model}**")
        parts.append(
            table(
                ["path", "B clients", "round trip median (ms)", "p90 (ms)", "μ(B) (req/s)",
                 "compute of one forward of B (ms)", "overhead per request (ms)"],
                rows,
            )
        )  # fmt: skip
        if ratio_rows:
            parts.append(
                table(["ours against", "B", "overhead ratio (ours / theirs)", "μ ratio"],
                      ratio_rows)
            )  # fmt: skip
        if skipped:
            parts.append("; ".join(skipped))
        if bds := e.get("breakdown_b1"):
            parts.append(breakdown_table(bds))
    tried_rows = []
    for model, e in d["models"].items():
        t = e.get("tried_adaptive_batcher")
        if t is None:
            continue
        for r, now in zip(t["rows"], e["ours"]["rows"], strict=True):
            tried_rows.append([model, r["clients"], now["rtt_ms_median"], r["rtt_ms_median"],
                               now["mu_per_s"], r["mu_per_s"]])  # fmt: skip
        bd, bt = e["breakdown_b1"], t["breakdown_b1"]
        tried_rows.append([model, "1, in the benchmark's process", bd["round_trip_ms"],
                           bt["round_trip_ms"], "-", "-"])  # fmt: skip
    if tried_rows:
        parts.append(f"**Tried, not adopted:** {d.get('tried', 'another batcher')}")
        parts.append(
            table(["model", "B", "round trip ours (ms)", "round trip tried (ms)", "μ ours",
                   "μ tried"], tried_rows)
        )  # fmt: skip
    if reps := d.get("repeats"):
        parts.append(repeats_table(d, reps))
    if d.get("noise"):
        parts.append(f"Noise: {d['noise']}.")
    note = (
        f"Batching wait {num(d['wait_ms'])} ms and at most {d['max_batch']} requests per forward, "
        "both servers; overhead = round-trip median − in-process compute of one forward of B "
        "requests (in_process: every client holds its own model, so no overhead is defined)."
    )
    return block(*parts, note, source("serving", d))


def _pairing(d: Mapping[str, Any] | None) -> str:
    if not d:
        return "-"
    lo, hi = d["ci95"]
    return f"{100 * d['diff']:+.1f} [{100 * lo:+.1f}, {100 * hi:+.1f}], p = {d['mcnemar_p']:.2g}"


def _mde(d: Mapping[str, Any] | None) -> str:
    if not d:
        return "-"
    return "none" if d.get("mde_pp") is None else f"{d['mde_pp']:.0f}"


def _short(d: Mapping[str, Any] | None) -> str:
    if not d:
        return "-"
    lo, hi = d["ci95"]
    return f"{100 * d['diff']:+.0f} [{100 * lo:+.0f}, {100 * hi:+.0f}]"


def _verdict(run: Mapping[str, Any]) -> tuple[str, str]:
    """The run's highest point success (with its forward rows per env step) and the methods
    that beat the reference cell by a paired test (a positive difference, McNemar p < 0.05;
    a bootstrap interval alone is not enough with this few discordant pairs)."""
    cells = list(run["cells"].values())
    best = max(cells, key=lambda c: (c["success"], -(c["rows_per_step"] or 0.0)))
    rows = "-" if best["rows_per_step"] is None else f"{best['rows_per_step']:.2f}"
    helping = [
        f"`{c['cell']}`"
        for c in cells
        if c.get("vs_reference")
        and c["vs_reference"]["diff"] > 0
        and c["vs_reference"]["mcnemar_p"] < 0.05
    ]
    return f"`{best['cell']}` {100 * best['success']:.0f}% ({rows} rows/step)", (
        ", ".join(helping) or "none"
    )


def _methods_overview(d: Data) -> str:
    """One row per run: IDR's E and its placebos, and which method is worth its forwards."""
    rows = []
    for run in d["runs"].values():
        cells = run["cells"]
        best, helping = _verdict(run)
        rows.append(
            [
                f"{run['member']} ({run['episodes_per_task']}/task)",
                run["reference"],
                _short(cells.get("E", {}).get("vs_reference")),
                _short(cells.get("random", {}).get("vs_E")),
                _short(cells.get("shuffled", {}).get("vs_E")),
                _short(cells.get("scale_free", {}).get("vs_reference")),
                best,
                helping,
            ]
        )
    return table(
        [
            "run (episodes per task)",
            "reference",
            "E − ref pp [95% CI]",
            "random − E",
            "shuffled − E",
            "scale_free − ref",
            "highest success",
            "beats ref (McNemar p < 0.05)",
        ],
        rows,
    )


def methods(d: Data) -> str:
    """methods.json: per member and suite, each method's success, its pairings against the
    reference cell and against IDR's mode E, and what it spends per executed env step; first
    one row per run, IDR's E against its placebos and the methods whose gain clears its
    interval."""
    parts = [f"*{d['label'].capitalize()}: no comparison here was declared before its data.*"]
    parts.append(_methods_overview(d))
    for run in d["runs"].values():
        ref = run["reference"]
        rows = [
            [
                f"`{c['cell']}`",
                f"{100 * c['success']:.0f} [{100 * c['ci95'][0]:.0f}, {100 * c['ci95'][1]:.0f}]",
                _pairing(c["vs_reference"]),
                _pairing(c["vs_E"]),
                _mde(c["vs_E"]),
                "-" if c["rows_per_step"] is None else f"{c['rows_per_step']:.2f}",
                "-" if c["ms_per_step"] is None else f"{c['ms_per_step']:.1f}",
            ]
            for c in run["cells"].values()
        ]
        n = run["episodes_per_task"]
        hw = ", ".join(run["hardware"])
        head = (
            f"**{run['member']}** on {run['suite']} ({len(run['tasks'])} tasks x {n} episodes "
            f"per cell; {hw}; run `{run['run_dir']}`; {run['errors']} error rows)"
        )
        parts += [
            head,
            table(
                [
                    "cell",
                    "success % [95% CI]",
                    f"Δ vs {ref} pp [95% CI], p",
                    "Δ vs E (same α) pp [95% CI], p",
                    "MDE vs E (pp)",
                    "rows / env step",
                    "ms / env step",
                ],
                rows,
            ),
        ]
    parts.append(source("methods", d))
    return block(*parts)


RENDERERS: dict[str, Callable[[Data], str]] = {
    f.__name__: f
    for f in (
        methods,
        faults,
        default_run,
        engine,
        tabletop_env,
        libero_env,
        libero_pro_step,
        env_server,
        calvin_env,
        policy_service,
        serving,
        shared_numerics,
        remote_backbone,
        report_scale,
        tracking_scale,
        cluster,
        slurm,
        perturbations,
        plugin_latency,
        idr_passes,
        gpu_idr_passes,
        gpu_rendering,
        tabletop_env_egl_h100,
        tiny_vla_alignment,
        portable_numerics,
        zoo_tabletop,
        zoo_metaworld,
        zoo_tabletop_pos,
        zoo_act_vision,
        zoo_smolvla_vision,
        zoo_metaworld_vision,
        paper_observations,
        confirmatory_metaworld,
        reliance_metaworld,
        zoo_training_metaworld,
        isa_spread,
        gpu_supply,
    )
}


def render(name: str, results: Path = RESULTS) -> str:
    """The Markdown for one marker; raises on a name without a renderer or a missing file."""
    if name not in RENDERERS:
        raise PluginError(f"unknown results marker {name!r}; known: {sorted(RENDERERS)}")
    path = results / f"{name}.json"
    if not path.is_file():
        raise PluginError(f"results marker {name!r}: {path} does not exist")
    try:
        return RENDERERS[name](json.loads(path.read_text()))
    except (KeyError, TypeError, ValueError, IndexError) as e:
        raise PluginError(f"results marker {name!r}: {path} has another shape ({e!r})") from e


# -- one figure in prose ------------------------------------------------------------------------


class _Each(list):
    """The items a filter selected: a key after it is looked up in each of them."""


_SEGMENT = re.compile(r"([^.\[\]]+)|\[([^\]]*)\]")


def lookup(data: Any, path: str) -> Any:
    """The value at ``path`` in ``data``: dotted keys; ``[KEY]`` for a key holding dots;
    ``[3]`` an index; ``[2:5]`` a slice; ``[*]`` every item; ``[cell=diagnose,task=pick_color]`` the list items whose
    fields equal those values (a key after a filter is looked up in each item it selected)."""
    value, pos = data, 0
    for m in _SEGMENT.finditer(path):
        if path[pos : m.start()].strip(".") or m.start() < pos:
            break
        pos = m.end()
        key, inner = m.group(1), m.group(2)
        if key is not None:
            value = _key(value, key.strip())
        elif re.fullmatch(r"-?\d+", inner.strip()):
            value = _each(value, lambda v, i=int(inner): v[i])
        elif re.fullmatch(r"-?\d*:-?\d*", inner.strip()):
            lo, hi = (int(x) if x else None for x in inner.split(":"))
            value = _each(value, lambda v, lo=lo, hi=hi: list(v)[lo:hi])
        elif inner.strip() == "*":
            value = _Each(value)
        elif "=" in inner:
            want = dict(kv.split("=", 1) for kv in inner.split(","))
            items = [x for x in value if all(str(x.get(k)) == v for k, v in want.items())]
            if not items:
                raise KeyError(f"no item of {path!r} has {want}")
            value = _Each(items)
        else:
            value = _key(value, inner)
    if path[pos:].strip(".") or pos == 0:
        raise KeyError(f"cannot read the path {path!r} past {path[:pos]!r}")
    return value


def _each(value: Any, get: Callable[[Any], Any]) -> Any:
    """``get`` of the value, or of each item a filter selected."""
    return _Each(get(v) for v in value) if isinstance(value, _Each) else get(value)


def _key(value: Any, key: str) -> Any:
    return _each(value, lambda v: v[key])


def _one(items: Any) -> Any:
    if len(items) != 1:
        raise ValueError(f"the filter selected {len(items)} items, not one")
    return items[0]


def _successes(items: Any) -> tuple[int, int]:
    return sum(int(t["successes"]) for t in items), sum(int(t["n"]) for t in items)


def wilson(k: int, n: int, z: float = 1.959963984540054) -> list[float]:
    """The Wilson score interval of ``k`` successes in ``n`` (the cards' per-task intervals)."""
    p, d = k / n, 1 + z * z / n
    half = z * (p * (1 - p) / n + z * z / (4 * n * n)) ** 0.5
    return [max(0.0, (p + z * z / (2 * n) - half) / d), min(1.0, (p + z * z / (2 * n) + half) / d)]


def fisher(rows: Any) -> float:
    """Fisher's exact test, two-sided, of two task rows' successes over n."""
    (k1, n1), (k2, n2) = (_successes([r]) for r in rows)
    k, n = k1 + k2, n1 + n2

    def prob(x: int) -> float:
        return math.comb(k, x) * math.comb(n - k, n1 - x) / math.comb(n, n1)

    seen = prob(k1)
    return sum(
        prob(x) for x in range(max(0, k - n2), min(k, n1) + 1) if prob(x) <= seen * 1.0000001
    )


def _scale(value: Any, f: float) -> Any:
    return [_scale(v, f) for v in value] if isinstance(value, list) else value * f


OPS: dict[str, Callable[[Any], Any]] = {
    "one": lambda v: _one(v),
    "sum": lambda v: sum(v.values() if isinstance(v, Mapping) else v),
    "min": lambda v: min(v),
    "max": lambda v: max(v),
    "mean": lambda v: statistics.fmean(v),
    "len": lambda v: len(v),
    "range": lambda v: [min(v), max(v)],
    "rate": lambda v: (lambda k, n: k / n)(*_successes(v)),
    "wilson": lambda v: wilson(*_successes(v)),
    "fisher": fisher,
    "x100": lambda v: _scale(v, 100),
    "minutes": lambda v: _scale(v, 1 / 60),
}


def spell(value: Any, spec: str | None) -> str:
    """One value as prose writes it: ``spec`` a Python format spec (:func:`num` without one); a
    minus is U+2212, a zero carries no sign; a pair is ``[a, b]`` (an interval), ``a-b`` after the
    ``range`` op."""
    if isinstance(value, list):
        return "[" + ", ".join(spell(v, spec) for v in value) + "]"
    if spec is None:
        text = num(value)
    else:
        if value == 0:
            spec = spec.replace("+", "")
        text = format(value, spec)
    text = re.sub(r"^-(?=0(?:\.0*)?%?$)", "", text)
    return text.replace("-", "\u2212")


def figure(name: str, path: str, ops: str = "", results: Path | None = None) -> str:
    """A ``{{ NAME:PATH | OPS }}`` marker's text: the value at PATH in ``benchmarks/results/NAME.json``
    through OPS, words applied in turn (``one`` of a filter's items, ``sum`` of a list or a map's values, ``min``, ``max``, ``mean``, ``len``, ``range``;
    ``rate`` and ``wilson`` of task rows' successes over n, ``fisher`` of two rows; ``x100``; ``minutes`` of seconds), the
    last word a format spec when it is no op (``.2f``, ``+.1f``, ``.0%``, ``.2g``)."""
    file = (results or RESULTS) / f"{name}.json"
    if not file.is_file():
        raise PluginError(f"figure {name}:{path}: {file} does not exist")
    try:
        value = lookup(json.loads(file.read_text()), path)
        words = ops.split()
        spec = words.pop() if words and words[-1] not in OPS else None
        for word in words:
            if word not in OPS:
                raise KeyError(f"unknown op {word!r}; known: {sorted(OPS)}")
            value = OPS[word](value)
        if isinstance(value, _Each):
            raise TypeError("a filter selected several values: add an op that makes one (sum)")
        ranged = "range" in words
        text = spell(list(value) if isinstance(value, list) else value, spec)
        return text.strip("[]").replace(", ", "-") if ranged else text
    except (KeyError, TypeError, ValueError, IndexError, ZeroDivisionError) as e:
        raise PluginError(f"figure {name}:{path} | {ops}: {e}") from e


def on_page_markdown(
    markdown: str, page: Page | None, config: MkDocsConfig | None, files: Files | None
) -> str:
    """MkDocs event: replace every results marker of the page by its table, every figure marker
    by its value."""
    where = page.file.src_uri if page is not None else "<markdown>"

    def one(m: re.Match[str]) -> str:
        try:
            return render(m.group(1))
        except PluginError as e:
            raise PluginError(f"{where}: {e}") from e

    def value(m: re.Match[str]) -> str:
        try:
            return figure(m.group(1), m.group(2).strip(), m.group(3) or "")
        except PluginError as e:
            raise PluginError(f"{where}: {e}") from e

    return FIGURE.sub(value, MARKER.sub(one, markdown))
