"""IDR's three passes on a GPU: one backbone call vs one batched 3B forward vs three calls.

The protocol of bench_idr_passes.py (the three variants interleaved round by round, medians),
on an accelerator: each timed ``IDRWrapper.infer`` starts and ends with
``torch.cuda.synchronize()``; ``wall`` is perf_counter around it (what an actor waits for),
``gpu`` is CUDA events recorded around it on the current stream. Observations start on the
host (as envs produce them); the backbones copy them to the device. Backbones:

- ``lerobot_act``: ACTPolicy built from its config (random weights, no hub), 96 px, 8-d state.
- ``tiny_vla``: checkpoints/tiny_vla through the project's LerobotBackbone (its processors on
  the device; do(S) in normalized space as in a run).
- ``pi05`` / ``pi0`` (``--pi``): PI05Config / PI0Config from config with random weights
  (PaliGemma 2B + 300M action expert, 2 cameras at 224 px, 10 flow steps). No tokenizer is
  available offline, so token ids are fed directly: the instruction's words hashed to ids, and
  for pi0.5 the state discretized into 256 bins written as tokens into the prompt (as pi0.5's
  processor does), padded to ``tokenizer_max_length``. The three passes share one noise draw.

dtypes: ``fp32`` (TF32 off) and ``bf16`` (torch.autocast for ACT and tiny_vla; for pi the
policy's own ``dtype="bfloat16"``, which keeps the vision tower in fp32 as lerobot does).

Writes ``benchmarks/results/gpu_idr_passes.json`` (and prints a table); each backbone runs in a
try block, so a failure is recorded in the JSON with its error and the others still run.
Usage: ``python benchmarks/bench_gpu.py [--device cuda] [--rounds 40] [--pi pi05,pi0] [--out PATH]``
(``--device cpu --tiny`` checks the script on a machine without a GPU, at toy sizes, and
writes to a new temporary folder unless ``--out`` is given).
lerobot 0.6.1's pi0/pi0.5 need transformers >=5.4,<5.6 (with 5.17 inference fails in
``pi_gemma.py``: ``create_causal_mask() got an unexpected keyword argument 'cache_position'``);
where the installed transformers is newer, run pi in a second process with 5.5.4 first on
PYTHONPATH and ``--skip act,tiny_vla --pi pi05,pi0 --merge`` to add to the same JSON.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import platform
import statistics
import sys
import time
import traceback
import zlib
from pathlib import Path
from typing import Any, ClassVar

import torch
from idr_core.features import (
    ACTION,
    IMAGE_PREFIX,
    OBS_LANGUAGE_ATTENTION_MASK,
    OBS_LANGUAGE_TOKENS,
    OBS_STATE,
)
from results_path import results_path

from workers.hardware import machine_record

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a plain script from a checkout that is not installed
    sys.path.insert(0, str(ROOT))
RESULTS = ROOT / "benchmarks" / "results" / "gpu_idr_passes.json"
VARIANTS = ("single", "batched_3pass", "sequential_3pass")
DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16}


def _to(x: Any, device: torch.device) -> torch.Tensor:
    return torch.as_tensor(x).to(device, non_blocking=True)


class ACTGpuBackbone:
    """A lerobot ACTPolicy behind the Backbone protocol, on ``device`` (random weights)."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset()
    can_batch = True
    crn_mode = "deterministic"

    def __init__(self, device: torch.device, image_size: int = 96, state_dim: int = 8) -> None:
        from lerobot.configs.types import FeatureType, PolicyFeature
        from lerobot.policies.act.configuration_act import ACTConfig
        from lerobot.policies.act.modeling_act import ACTPolicy

        cfg = ACTConfig(
            input_features={
                f"{IMAGE_PREFIX}agentview": PolicyFeature(
                    type=FeatureType.VISUAL, shape=(3, image_size, image_size)
                ),
                OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(state_dim,)),
            },
            output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(7,))},
            pretrained_backbone_weights=None,
            device=str(device),
        )
        self.device = device
        self.policy = ACTPolicy(cfg).to(device).eval()
        self.name = "lerobot_act"
        self.cameras = ("agentview",)
        self.image_size = image_size
        self.state_dim = state_dim
        self.n_params = sum(p.numel() for p in self.policy.parameters())

    def reset(self) -> None:
        self.policy.reset()

    def make_noise(self, batch_size: int, seed: int) -> None:
        return None  # ACT is deterministic at inference

    @torch.inference_mode()
    def predict_chunk(self, obs: Any, noise: Any = None, intervention: Any = None) -> torch.Tensor:
        batch = {
            f"{IMAGE_PREFIX}agentview": _to(obs.images["agentview"], self.device),
            OBS_STATE: _to(obs.state, self.device),
        }
        return self.policy.predict_action_chunk(batch)


class PiGpuBackbone:
    """lerobot's pi0 / pi0.5 from config with random weights, token ids fed directly."""

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset()
    can_batch = True
    crn_mode = "shared_noise"

    def __init__(
        self,
        variant: str,
        device: torch.device,
        dtype: str = "bfloat16",
        image_size: int = 224,
        cameras: tuple[str, ...] = ("agentview", "wrist"),
        state_dim: int = 8,
        action_dim: int = 7,
        small: bool = False,
    ) -> None:
        from lerobot.configs.types import FeatureType, PolicyFeature

        if variant == "pi05":
            from lerobot.policies.pi05.configuration_pi05 import PI05Config as Config
            from lerobot.policies.pi05.modeling_pi05 import PI05Policy as Policy
        elif variant == "pi0":
            from lerobot.policies.pi0.configuration_pi0 import PI0Config as Config
            from lerobot.policies.pi0.modeling_pi0 import PI0Policy as Policy
        else:
            raise ValueError(f"--pi {variant!r}: use pi05 or pi0")
        extra: dict[str, Any] = {}
        if small:  # CPU smoke test of this code path: 1-layer Gemmas, few steps
            import importlib

            mod = importlib.import_module(Policy.__module__)
            full = mod.get_gemma_config

            def shallow(v: str) -> Any:
                c = full(v)
                c.depth, c.mlp_dim = 1, 256
                return c

            mod.get_gemma_config = shallow
            extra = {"num_inference_steps": 2, "chunk_size": 10, "n_action_steps": 10}
        cfg = Config(
            input_features={
                **{
                    f"{IMAGE_PREFIX}{c}": PolicyFeature(
                        type=FeatureType.VISUAL, shape=(3, image_size, image_size)
                    )
                    for c in cameras
                },
                OBS_STATE: PolicyFeature(type=FeatureType.STATE, shape=(state_dim,)),
            },
            output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,))},
            dtype=dtype,
            device=str(device),
            image_resolution=(image_size, image_size),
            **extra,
        )
        self.config = cfg
        self.variant = variant
        self.device = device
        t0 = time.perf_counter()
        # parameters are created (and randomly initialised) on the device directly
        with torch.device(device):
            self.policy = Policy(cfg).eval()
        self.build_s = time.perf_counter() - t0
        self.name = f"lerobot_{variant}"
        self.cameras = cameras
        self.image_size = image_size
        self.state_dim = state_dim
        self.n_params = sum(p.numel() for p in self.policy.parameters())
        self.max_len = int(cfg.tokenizer_max_length)

    def reset(self) -> None:
        self.policy.reset()

    def make_noise(self, batch_size: int, seed: int) -> torch.Tensor:
        gen = torch.Generator().manual_seed(seed)
        shape = (batch_size, self.config.chunk_size, self.config.max_action_dim)
        return torch.randn(shape, generator=gen).to(self.device)

    def _tokens(self, instruction: list[str], state: torch.Tensor) -> tuple[Any, Any]:
        """Prompt token ids and mask, (B, tokenizer_max_length), without a tokenizer."""
        rows = []
        for i, text in enumerate(instruction):
            ids = [2] + [zlib.crc32(w.encode()) % 250_000 + 3 for w in f"Task: {text}".split()]
            if self.variant == "pi05":  # "State: <256 bins>;\nAction: " (pi0.5's prompt)
                bins = torch.bucketize(state[i].clamp(-1, 1), torch.linspace(-1, 1, 257)[1:-1])
                ids += [101] + [int(b) + 200 for b in bins] + [102, 103]
            rows.append(ids[: self.max_len])
        tokens = torch.zeros(len(rows), self.max_len, dtype=torch.long)
        mask = torch.zeros(len(rows), self.max_len, dtype=torch.bool)
        for i, ids in enumerate(rows):
            tokens[i, : len(ids)] = torch.tensor(ids)
            mask[i, : len(ids)] = True
        return tokens, mask

    @torch.inference_mode()
    def predict_chunk(self, obs: Any, noise: Any = None, intervention: Any = None) -> torch.Tensor:
        state = torch.as_tensor(obs.state).float()
        tokens, mask = self._tokens(list(obs.instruction), state)
        batch: dict[str, Any] = {
            f"{IMAGE_PREFIX}{c}": _to(obs.images[c], self.device) for c in self.cameras
        }
        batch[OBS_LANGUAGE_TOKENS] = _to(tokens, self.device)
        batch[OBS_LANGUAGE_ATTENTION_MASK] = _to(mask, self.device)
        batch[OBS_STATE] = _to(state, self.device)
        kwargs = {} if noise is None else {"noise": noise}
        return self.policy.predict_action_chunk(batch, **kwargs)


def _obs(cameras: tuple[str, ...], image_size: int, state_dim: int, batch: int, seed: int = 0):
    from workers.backbones.base import Observation

    gen = torch.Generator().manual_seed(seed)
    return Observation(
        images={c: torch.rand(batch, 3, image_size, image_size, generator=gen) for c in cameras},
        state=torch.rand(batch, state_dim, generator=gen) * 2 - 1,
        instruction=["pick up the red cube and put it in the basket"] * batch,
    )


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def measure(
    backbone: Any,
    obs: Any,
    device: torch.device,
    rounds: int,
    warmup: int,
    autocast: torch.dtype | None = None,
) -> dict[str, Any]:
    from idr_core.interventions import InterventionConfig
    from idr_core.refiner import RefinerConfig

    from workers.policy.wrapper import IDRWrapper

    state_space = "normalized" if "normalized" in backbone.native_intervention_spaces else "raw"
    iv = InterventionConfig(state_space=state_space)
    pols = {
        "single": IDRWrapper(backbone, RefinerConfig(mode="baseline"), iv),
        "batched_3pass": IDRWrapper(backbone, RefinerConfig(mode="E"), iv, batched=True),
        "sequential_3pass": IDRWrapper(backbone, RefinerConfig(mode="E"), iv, batched=False),
    }
    cuda = device.type == "cuda"
    ctx = (
        (lambda: torch.autocast(device.type, dtype=autocast))
        if autocast is not None
        else contextlib.nullcontext
    )
    wall: dict[str, list[float]] = {k: [] for k in VARIANTS}
    gpu: dict[str, list[float]] = {k: [] for k in VARIANTS}
    for r in range(warmup + rounds):
        order = VARIANTS[r % 3 :] + VARIANTS[: r % 3]  # rotate who goes first
        for name in order:
            start = torch.cuda.Event(enable_timing=True) if cuda else None
            end = torch.cuda.Event(enable_timing=True) if cuda else None
            _sync(device)
            t0 = time.perf_counter()
            if start is not None:
                start.record()
            with ctx():
                pols[name].infer(obs, step_seed=r)
            if end is not None:
                end.record()
            _sync(device)
            ms = (time.perf_counter() - t0) * 1e3
            if r >= warmup:
                wall[name].append(ms)
                if start is not None and end is not None:
                    gpu[name].append(start.elapsed_time(end))
    # one more call of each: peak memory, and batched == sequential on the factual chunk
    peak: dict[str, float] = {}
    steps = {}
    for name in VARIANTS:
        if cuda:
            torch.cuda.reset_peak_memory_stats(device)
        with ctx():
            steps[name] = pols[name].infer(obs, step_seed=12345)
        _sync(device)
        if cuda:
            peak[name] = torch.cuda.max_memory_allocated(device) / 2**20

    def maxdiff(a: Any, b: Any) -> float:
        return float((torch.as_tensor(a).float() - torch.as_tensor(b).float()).abs().max())

    b, s = steps["batched_3pass"], steps["sequential_3pass"]
    med = {k: statistics.median(v) for k, v in wall.items()}
    out: dict[str, Any] = {
        "median_ms": med,
        "p10_ms": {k: _q(v, 0.1) for k, v in wall.items()},
        "p90_ms": {k: _q(v, 0.9) for k, v in wall.items()},
        "ratio_batched_vs_single": med["batched_3pass"] / med["single"],
        "ratio_sequential_vs_single": med["sequential_3pass"] / med["single"],
        "batched_vs_sequential_max_abs_diff": {
            "a_base": maxdiff(b.a_base, s.a_base),
            "a_no_img": maxdiff(b.a_no_img, s.a_no_img),
            "a_no_prop": maxdiff(b.a_no_prop, s.a_no_prop),
        },
        "rounds": rounds,
        "warmup": warmup,
    }
    if gpu["single"]:
        gmed = {k: statistics.median(v) for k, v in gpu.items()}
        out["gpu_event_median_ms"] = gmed
        out["gpu_ratio_batched_vs_single"] = gmed["batched_3pass"] / gmed["single"]
        out["gpu_ratio_sequential_vs_single"] = gmed["sequential_3pass"] / gmed["single"]
    if peak:
        out["peak_mem_mib"] = peak
    return out


def _q(v: list[float], q: float) -> float:
    s = sorted(v)
    return s[int(q * (len(s) - 1))]


def _machine(device: torch.device) -> dict[str, Any]:
    m: dict[str, Any] = {
        **machine_record(str(device)),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "device": str(device),
        "threads": torch.get_num_threads(),
        "tf32_matmul": torch.backends.cuda.matmul.allow_tf32,
        "cudnn_tf32": torch.backends.cudnn.allow_tf32,
    }
    if device.type == "cuda":
        p = torch.cuda.get_device_properties(device)
        m.update(
            device_name=p.name,
            sm_count=p.multi_processor_count,
            memory_gib=round(p.total_memory / 2**30, 1),
            cuda=torch.version.cuda,
            cudnn=torch.backends.cudnn.version(),
        )
    for pkg in ("lerobot", "transformers", "numpy"):
        with contextlib.suppress(Exception):
            from importlib.metadata import version

            m[pkg] = version(pkg)
    return m


def _hide_broken_optional(names: tuple[str, ...]) -> dict[str, str]:
    """lerobot imports optional packages it finds installed (peft in its policy factory); one
    built against another transformers than the one in use would stop every lerobot import.
    Such a package is hidden (None in sys.modules makes find_spec answer None), not needed here."""
    import importlib

    hidden = {}
    for name in names:
        try:
            importlib.import_module(name)
        except ModuleNotFoundError:
            pass
        except Exception as e:
            sys.modules[name] = None  # type: ignore[assignment]
            hidden[name] = f"{type(e).__name__}: {e}"[:300]
    return hidden


def merge_results(prev: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """``prev`` kept, the new run's machine block appended to ``merged_runs``; the backbones the
    new run measures are added to (or replace those of) ``prev["backbones"]``."""
    out = {**prev, "backbones": dict(prev.get("backbones", {}))}
    out["merged_runs"] = [*prev.get("merged_runs", []), {"machine": new["machine"]}]
    return out


def _run(results: dict[str, Any], key: str, fn: Any) -> None:
    """Run one backbone's measurements; record the error instead of stopping."""
    t0 = time.perf_counter()
    try:
        results["backbones"][key] = fn()
    except Exception as e:
        traceback.print_exc()
        results["backbones"][key] = {
            "error": f"{type(e).__name__}: {e}"[:2000],
            "traceback_tail": traceback.format_exc()[-3000:],
        }
    results["backbones"][key]["section_s"] = round(time.perf_counter() - t0, 1)
    # which run measured it: 0 = the one of "machine", i = "merged_runs"[i - 1]
    results["backbones"][key]["run"] = len(results.get("merged_runs", []))
    print(f"[{key}] done in {time.perf_counter() - t0:.1f} s", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--rounds", type=int, default=40)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--dtypes", default="fp32,bf16")
    ap.add_argument("--batch-sizes", default="1,8", help="envs per inference (ACT, tiny_vla)")
    ap.add_argument("--skip", default="", help="comma list of: act, tiny_vla")
    ap.add_argument("--pi", default="", help="comma list of pi05, pi0 (large: GPU only)")
    ap.add_argument("--pi-dtypes", default="bf16")
    ap.add_argument("--pi-batch-sizes", default="1,4")
    ap.add_argument("--pi-rounds", type=int, default=15)
    ap.add_argument("--tiny", action="store_true", help="toy sizes, for a CPU check")
    ap.add_argument(
        "--out",
        type=Path,
        default=None,
        help=f"default: {RESULTS.relative_to(ROOT)}; with --tiny a new temporary folder",
    )
    ap.add_argument(
        "--merge",
        action="store_true",
        help="add to an existing --out (e.g. pi run in another process with its own transformers)",
    )
    args = ap.parse_args()
    args.out = results_path(RESULTS, args.out, "--tiny" if args.tiny else None)

    device = torch.device(args.device)
    torch.backends.cuda.matmul.allow_tf32 = False  # fp32 means fp32
    torch.backends.cudnn.allow_tf32 = False
    dtypes = [d for d in args.dtypes.split(",") if d]
    sizes = [int(b) for b in args.batch_sizes.split(",") if b]
    skip = set(args.skip.split(","))
    hidden = _hide_broken_optional(("peft",))
    results: dict[str, Any] = {
        "machine": {**_machine(device), "hidden_broken_optional": hidden},
        "protocol": (
            "IDRWrapper.infer timed per call: cuda synchronize, perf_counter + CUDA events, "
            "sync; variants interleaved (order rotated per round); medians over rounds "
            "after warmup. single = mode baseline (1 pass of B), batched_3pass = one 3B "
            "forward, sequential_3pass = three B forwards; IDR mode E, do(V)/do(S) = zero. "
            "Observations start on the host. bf16: torch.autocast for ACT/tiny_vla, the "
            "policy's dtype='bfloat16' for pi0/pi0.5."
        ),
        "backbones": {},
    }

    if args.merge and args.out.exists():
        results = merge_results(json.loads(args.out.read_text()), results)

    def save() -> None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(results, indent=2) + "\n")

    if "act" not in skip:
        act = ACTGpuBackbone(device, image_size=32 if args.tiny else 96)
        for dt in dtypes:
            for b in sizes:

                def run_act(dt: str = dt, b: int = b) -> dict[str, Any]:
                    o = _obs(act.cameras, act.image_size, act.state_dim, b)
                    ac = DTYPES[dt] if dt != "fp32" else None
                    r = measure(act, o, device, args.rounds, args.warmup, autocast=ac)
                    r.update(params_millions=act.n_params / 1e6, batch=b, dtype=dt)
                    r["image_size"] = act.image_size
                    return r

                _run(results, f"lerobot_act_{act.image_size}px_{dt}_B{b}", run_act)
                save()
        del act
    tiny = ROOT / "checkpoints" / "tiny_vla"
    if "tiny_vla" not in skip and tiny.is_dir():
        tiny_holder: dict[str, Any] = {}

        def load_tiny() -> Any:
            if "bb" not in tiny_holder:
                from workers.backbones.lerobot import LerobotBackbone

                tiny_holder["bb"] = LerobotBackbone(str(tiny), device=str(device))
            return tiny_holder["bb"]

        for dt in dtypes:
            for b in sizes:

                def run_tiny(dt: str = dt, b: int = b) -> dict[str, Any]:
                    bb = load_tiny()
                    o = _obs(bb.cameras, 96, bb.state_dim, b)
                    ac = DTYPES[dt] if dt != "fp32" else None
                    r = measure(bb, o, device, args.rounds, args.warmup, autocast=ac)
                    r.update(batch=b, dtype=dt, crn_mode=bb.crn_mode, do_state_space="normalized")
                    return r

                _run(results, f"tiny_vla_lerobot_adapter_{dt}_B{b}", run_tiny)
                save()
    holder: dict[str, Any] = {}  # the pi policy in use
    for variant in [v for v in args.pi.split(",") if v]:
        for dt in [d for d in args.pi_dtypes.split(",") if d]:
            holder.clear()

            def build_pi(variant: str = variant, dt: str = dt) -> dict[str, Any]:
                if device.type == "cuda":
                    torch.cuda.empty_cache()
                pi = PiGpuBackbone(
                    variant,
                    device,
                    dtype={"bf16": "bfloat16", "fp32": "float32"}[dt],
                    image_size=56 if args.tiny else 224,
                    small=args.tiny,
                )
                holder["pi"] = pi
                return {
                    "build_s": round(pi.build_s, 1),
                    "params_millions": pi.n_params / 1e6,
                    "param_dtypes": sorted({str(p.dtype) for p in pi.policy.parameters()}),
                }

            _run(results, f"lerobot_{variant}_{dt}_build", build_pi)
            save()
            if "pi" not in holder:
                continue
            for b in [int(x) for x in args.pi_batch_sizes.split(",") if x]:

                def run_pi(b: int = b, dt: str = dt) -> dict[str, Any]:
                    pi = holder["pi"]
                    o = _obs(pi.cameras, pi.image_size, pi.state_dim, b)
                    r = measure(pi, o, device, args.pi_rounds, min(args.warmup, 3))
                    cfg = pi.config
                    r.update(
                        batch=b,
                        dtype=dt,
                        image_size=pi.image_size,
                        cameras=len(pi.cameras),
                        num_inference_steps=cfg.num_inference_steps,
                        chunk_size=cfg.chunk_size,
                        tokenizer_max_length=cfg.tokenizer_max_length,
                        params_millions=pi.n_params / 1e6,
                    )
                    return r

                _run(results, f"lerobot_{variant}_{dt}_B{b}", run_pi)
                save()
            holder.clear()
            if device.type == "cuda":
                torch.cuda.empty_cache()
    save()

    print(
        f"{'backbone':<36} {'single ms':>10} {'batched ms':>11} {'seq ms':>9} "
        f"{'batched/1':>10} {'seq/1':>7}"
    )
    for name, r in results["backbones"].items():
        if "median_ms" not in r:
            if "error" in r:
                print(f"{name:<36} ERROR {r['error'][:120]}")
            continue
        m = r["median_ms"]
        print(
            f"{name:<36} {m['single']:>10.2f} {m['batched_3pass']:>11.2f} "
            f"{m['sequential_3pass']:>9.2f} {r['ratio_batched_vs_single']:>10.2f} "
            f"{r['ratio_sequential_vs_single']:>7.2f}"
        )
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
