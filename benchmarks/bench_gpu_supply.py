"""The model side of the throughput curve: μ(B), inferences per second one device serves when
each forward takes B observations, without IDR (B rows) and with IDR's triple (3B rows, one
shared noise draw), eager and compiled; peak device memory per B; the idr policy plugin's
per-chunk latency at B = 1.

Models (lerobot 0.6.1 classes, random weights built from their configs, bf16 on a GPU):
``pi05`` and ``pi0`` (PaliGemma 2B + 300M action expert, 2 cameras at 224 px, 10 flow steps,
token ids fed directly: no tokenizer offline; ``bench_gpu.PiGpuBackbone``), ``smolvla`` when
SmolVLM2's config and processor files are given (``--smolvla-vlm DIR``: lerobot asks the hub
for them even without weights; otherwise recorded as skipped with that reason).

Units (in the JSON and the docs): an *inference* is one observation in, one action chunk out
(with IDR: three rows of one forward). ``mu_inf_per_s[B] = B / t(B)``; env steps per second at
``k`` actions executed per inference: ``k * mu`` (k = 5, 10: the unit of the per-core simulator
rates). Compile: ``torch.compile`` of the model's ``sample_actions`` (what lerobot's
``compile_model`` switch does), mode ``--compile-mode``; the first calls' time beyond the eager
model's is reported apart as ``compile_s``.

Robust by design (one JSON, never a crash of the whole run): a model name the script does not
know, a model that cannot be built, a B that does not fit in memory: each recorded as
``skipped`` with the reason, the others still run, and the JSON is rewritten after each step.

``--dry``: the same code paths on the CPU at toy sizes (1-layer Gemmas, 56 px, B = 1, 2,
``torch.compile`` with the ``eager`` backend: traced by dynamo, no code generated), in seconds: CI runs it, so a timed path that goes away fails there.
Its JSON goes to a new temporary folder (printed) unless ``--out`` is given: toy CPU figures
never replace the committed device measurement.

Usage (device): ``python benchmarks/bench_gpu_supply.py --out benchmarks/results/gpu_supply.json``
(defaults: pi05, pi0, smolvla; B = 1..32; eager and compiled. On an H200 pi0.5's eager pass
took about 90 s and compiling six shapes more than 440 s: pass ``--compile-batches 1,32`` and
``--budget-s`` inside a lease.)
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
import traceback
from pathlib import Path
from typing import Any

import torch

ROOT = Path(__file__).resolve().parents[1]
for p in (ROOT, ROOT / "benchmarks"):  # run as a plain script from a checkout
    if str(p) not in sys.path:
        sys.path.insert(0, str(p))

from bench_gpu import PiGpuBackbone, _hide_broken_optional, _machine, _obs, _sync  # noqa: E402
from results_path import results_path  # noqa: E402

RESULTS = ROOT / "benchmarks" / "results" / "gpu_supply.json"
KNOWN = ("pi05", "pi0", "smolvla")
ACTIONS_PER_INFERENCE = (5, 10)
UNITS = {
    "mu_inf_per_s": "inferences per second: observations in, action chunks out (IDR: 3 rows each)",
    "env_steps_per_s": "mu x k actions executed per inference, k in actions_per_inference",
    "ms": "wall milliseconds per forward, cuda-synchronized, median over rounds",
    "peak_mem_gib": "torch.cuda.max_memory_allocated during one forward at that B",
}


def _oom(exc: BaseException) -> bool:
    return type(exc).__name__ == "OutOfMemoryError" or "out of memory" in str(exc).lower()


def _timed(fn: Any, device: torch.device, rounds: int, warmup: int) -> tuple[list[float], float]:
    """Wall ms per call (synchronized) after ``warmup`` calls; and the warm-up's seconds."""
    t0 = time.perf_counter()
    for _ in range(warmup):
        fn()
    _sync(device)
    warm_s = time.perf_counter() - t0
    out = []
    for _ in range(rounds):
        _sync(device)
        t = time.perf_counter()
        fn()
        _sync(device)
        out.append((time.perf_counter() - t) * 1e3)
    return out, warm_s


def supply(
    backbone: Any, device: torch.device, batches: list[int], rounds: int, warmup: int
) -> dict[str, Any]:
    """μ(B) without and with IDR's triple for one built model (eager or compiled)."""
    from idr_core.refiner import RefinerConfig

    from workers.policy.wrapper import IDRWrapper

    single = IDRWrapper(backbone, RefinerConfig(mode="baseline"))
    triple = IDRWrapper(backbone, RefinerConfig(mode="E", tau=1e9), batched=True)
    per_b: dict[str, Any] = {}
    first_call_s = None
    warmup_s = 0.0
    for b in batches:
        obs = _obs(backbone.cameras, backbone.image_size, backbone.state_dim, b)
        row: dict[str, Any] = {"batch": b}
        for name, pol in (("base", single), ("idr", triple)):
            try:
                if device.type == "cuda":
                    torch.cuda.empty_cache()
                    torch.cuda.reset_peak_memory_stats(device)
                ms, warm_s = _timed(
                    lambda p=pol, o=obs: p.infer(o, step_seed=1), device, rounds, warmup
                )
                if first_call_s is None:
                    first_call_s = warm_s
                warmup_s += warm_s
                med = statistics.median(ms)
                row[name] = {
                    "ms": med,
                    "ms_p90": sorted(ms)[int(0.9 * (len(ms) - 1))],
                    "rows_per_forward": b if name == "base" else 3 * b,
                    "mu_inf_per_s": b / (med / 1e3),
                    "env_steps_per_s": {str(k): k * b / (med / 1e3) for k in ACTIONS_PER_INFERENCE},
                }
                if device.type == "cuda":
                    row[name]["peak_mem_gib"] = torch.cuda.max_memory_allocated(device) / 2**30
            except Exception as exc:  # a B too large for the device: skipped, the rest go on
                if not _oom(exc):
                    raise
                row[name] = {"skipped": f"out of device memory at {b} observations: {exc}"[:300]}
        if "ms" in row.get("base", {}) and "ms" in row.get("idr", {}):
            row["idr_vs_base"] = row["idr"]["ms"] / row["base"]["ms"]
        per_b[str(b)] = row
    mus = [r["idr"]["mu_inf_per_s"] for r in per_b.values() if "mu_inf_per_s" in r.get("idr", {})]
    return {
        "per_batch": per_b,
        "first_calls_s": first_call_s,
        "warmup_s": warmup_s,  # every B's warm-up calls: a compiled model's (re)compilations
        "mu_idr_max": max(mus) if mus else None,
        "b_at_mu_idr_max": next(
            (int(k) for k, r in per_b.items() if r.get("idr", {}).get("mu_inf_per_s") == max(mus)),
            None,
        )
        if mus
        else None,
    }


def build(name: str, device: torch.device, dry: bool, compiled: str | None, vlm: str | None) -> Any:
    if name in ("pi05", "pi0"):
        if dry:  # lerobot's classes at tiny widths (the tests' shrink of its Gemma table)
            _tiny_gemmas()
        bb = PiGpuBackbone(
            name,
            device,
            dtype="float32" if device.type == "cpu" else "bfloat16",
            image_size=56 if dry else 224,
        )
        if compiled:  # what lerobot's compile_model does: torch.compile of sample_actions
            model = bb.policy.model
            kw = {"backend": "eager"} if compiled == "eager" else {"mode": compiled}
            model.sample_actions = torch.compile(model.sample_actions, **kw)
        return bb
    if name == "smolvla":
        if not vlm:
            raise LookupError(
                "SmolVLA needs SmolVLM2's config and processor files (its vlm_model_name) even "
                "without weights, which lerobot asks the hub for; no hub here: give "
                "--smolvla-vlm DIR (a local copy of HuggingFaceTB/SmolVLM2-500M-Video-Instruct's "
                "config and processor files)"
            )
        raise LookupError(f"--smolvla-vlm {vlm}: SmolVLA timing is not implemented in this script")
    raise LookupError(f"unknown model {name!r}; known: {', '.join(KNOWN)}")


def _tiny_gemmas() -> None:
    from _pytest.monkeypatch import MonkeyPatch

    from training.toy_checkpoints import tiny_pi_gemma

    tiny_pi_gemma(MonkeyPatch())  # for the rest of this process: the dry run only


def plugin_latency(device: torch.device, rounds: int, work: Path) -> dict[str, Any]:
    """The idr policy type's per-chunk latency at B = 1 (preprocessor + predict_action_chunk +
    postprocessor), base (mode baseline) vs IDR (mode E), for the shipped tiny VLA."""
    from lerobot_policy_idr.loading import load_idr
    from lerobot_policy_idr.wrap import main as wrap_main

    base = ROOT / "checkpoints" / "tiny_vla"
    out: dict[str, Any] = {"base": "tiny_vla"}
    for mode in ("baseline", "E"):
        folder = work / f"idr_{mode}"
        args = [str(base), str(folder), "--mode", mode, "--device", str(device.type)]
        args += ["--diagnostics-dir", str(work / "diag")]
        assert wrap_main([*args, *(["--tau", "1e9"] if mode == "E" else [])]) == 0
        policy, pre, post = load_idr(folder, str(device))
        obs = {k: torch.rand(1, *f.shape) for k, f in policy.config.input_features.items()}
        obs["task"] = ["pick up the red cube"]

        def chunk(policy: Any = policy, pre: Any = pre, post: Any = post, obs: Any = obs) -> None:
            with torch.inference_mode():
                post(policy.predict_action_chunk(pre(dict(obs))))

        ms, _ = _timed(chunk, device, rounds, 3)
        out[mode] = {"ms": statistics.median(ms), "ms_p90": sorted(ms)[int(0.9 * (len(ms) - 1))]}
        policy.sidecar.flush()  # before the temporary folder goes
    out["idr_vs_base"] = out["E"]["ms"] / out["baseline"]["ms"]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--models", default="pi05,pi0,smolvla")
    ap.add_argument("--batches", default="1,2,4,8,16,32")
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument(
        "--compile-mode", default="default", help="torch.compile mode ('' : eager only)"
    )
    ap.add_argument(
        "--compile-batches", default=None, help="B values compiled (default: all of --batches)"
    )
    ap.add_argument("--smolvla-vlm", default=None, help="local SmolVLM2 config + processor dir")
    ap.add_argument(
        "--budget-s",
        type=float,
        default=None,
        help="start no model or mode after this many seconds (a device lease's window); what "
        "was not started is recorded as skipped with this reason",
    )
    ap.add_argument("--dry", action="store_true", help="CPU, toy sizes, B = 1, 2: a CI check")
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help=f"default: {RESULTS.relative_to(ROOT)}; with --dry a new temporary folder",
    )
    args = ap.parse_args(argv)
    args.out = results_path(RESULTS, args.out, "--dry" if args.dry else None)
    if args.dry:
        args.device, args.batches, args.rounds, args.warmup = "cpu", "1,2", 2, 1
        args.compile_mode, args.compile_batches = "eager", "1"
    device = torch.device(args.device)
    batches = [int(b) for b in args.batches.split(",") if b]
    compile_batches = [int(b) for b in (args.compile_batches or args.batches).split(",") if b]
    hidden = _hide_broken_optional(("peft",))
    t_start = time.perf_counter()
    results: dict[str, Any] = {
        "machine": {**_machine(device), "hidden_broken_optional": hidden},
        "dry": args.dry,
        "units": UNITS,
        "actions_per_inference": list(ACTIONS_PER_INFERENCE),
        "batches": batches,
        "models": {},
    }

    def save() -> None:
        results["total_s"] = round(time.perf_counter() - t_start, 1)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2) + "\n")

    def spent() -> str | None:
        """Why nothing more may start (``--budget-s`` spent), or None."""
        if args.budget_s is not None and time.perf_counter() - t_start > args.budget_s:
            return f"not started: --budget-s {args.budget_s:g} s spent"
        return None

    # "eager", then "compiled" (torch.compile with --compile-mode; the eager backend when dry)
    modes = {"eager": None, **({"compiled": args.compile_mode} if args.compile_mode else {})}
    results["compile_mode"] = args.compile_mode or None
    for name in [m for m in args.models.split(",") if m]:
        entry: dict[str, Any] = {}
        results["models"][name] = entry
        for mode, how in modes.items():
            if reason := spent():
                entry[mode] = {"skipped": reason}
                save()
                continue
            t0 = time.perf_counter()
            try:
                bb = build(name, device, args.dry, how, args.smolvla_vlm)
                entry["params_millions"] = bb.n_params / 1e6
                entry[mode] = {"build_s": round(time.perf_counter() - t0, 1)}
                sizes = batches if how is None else compile_batches
                entry[mode].update(supply(bb, device, sizes, args.rounds, args.warmup))
                if how is not None:  # the warm-up calls paid the compilations (one per shape)
                    eager = entry.get("eager", {}).get("per_batch", {})
                    eager_warm = (
                        sum(
                            entry["eager"]["warmup_s"] / max(len(eager), 1) for _ in compile_batches
                        )
                        if eager
                        else 0.0
                    )
                    entry[mode]["compile_s"] = round(entry[mode]["warmup_s"] - eager_warm, 1)
                    entry[mode]["compile_mode"] = how
                del bb
            except LookupError as e:  # unknown, or cannot be built here: skipped with the reason
                entry["skipped"] = str(e)
                break
            except Exception as e:
                traceback.print_exc()
                entry[mode] = {"skipped": f"{type(e).__name__}: {e}"[:1000]}
            finally:
                if device.type == "cuda":
                    torch.cuda.empty_cache()
                save()
    try:
        if reason := spent():
            raise TimeoutError(reason)
        with tempfile.TemporaryDirectory() as tmp:
            results["plugin_latency_B1"] = plugin_latency(device, args.rounds * 2, Path(tmp))
    except Exception as e:
        traceback.print_exc()
        results["plugin_latency_B1"] = {"skipped": f"{type(e).__name__}: {e}"[:1000]}
    save()
    for name, entry in results["models"].items():
        if "skipped" in entry:
            print(f"{name:<8} skipped: {entry['skipped'][:100]}")
            continue
        for mode in modes:
            for b, row in entry.get(mode, {}).get("per_batch", {}).items():
                base, idr = row.get("base", {}), row.get("idr", {})
                if "ms" in base and "ms" in idr:
                    print(
                        f"{name:<8} {mode:<8} B={b:>3} base {base['ms']:8.1f} ms "
                        f"({base['mu_inf_per_s']:7.1f} inf/s)  IDR {idr['ms']:8.1f} ms "
                        f"({idr['mu_inf_per_s']:7.1f} inf/s)  x{row['idr_vs_base']:.2f}"
                    )
    print(f"written to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
