"""Cost of IDR's three passes against one backbone call: batched (one 3B forward) vs sequential.

Backbones: the closed-form fake, and a lerobot ACT policy built offline from its config
(96x96 image, 8-d state, 7-d action, ``pretrained_backbone_weights=None``: random weights, the
cost is the same). Each measurement interleaves the three variants (single, batched, sequential)
round by round so that load on the machine hits them alike; the ratios are what to compare.

Writes ``benchmarks/results/idr_passes.json`` (and prints a table).
Usage: ``python benchmarks/bench_idr_passes.py [--rounds 30] [--out PATH]``
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path
from typing import Any, ClassVar

import torch
from idr_core.features import ACTION, IMAGE_PREFIX, OBS_STATE
from idr_core.refiner import RefinerConfig

from workers.backbones.base import Observation
from workers.backbones.fakes import FakeMarkerBackbone
from workers.hardware import machine_record
from workers.policy.wrapper import IDRWrapper

RESULTS = Path(__file__).parent / "results" / "idr_passes.json"


class ACTBenchBackbone:
    """Benchmark-only adapter: a lerobot ACTPolicy called through ``predict_action_chunk``.

    Random weights, no processors (ACT normalizes in its processors, which cost little next to
    the model). The project's lerobot adapter with processors lives in workers.backbones.
    """

    native_intervention_spaces: ClassVar[frozenset[str]] = frozenset()
    can_batch = True

    def __init__(self, image_size: int = 96, state_dim: int = 8, action_dim: int = 7) -> None:
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
            output_features={ACTION: PolicyFeature(type=FeatureType.ACTION, shape=(action_dim,))},
            pretrained_backbone_weights=None,
            device="cpu",
        )
        self.policy = ACTPolicy(cfg).eval()
        self.name = "lerobot_act"
        self.chunk_len = cfg.chunk_size
        self.action_dim = action_dim
        self.n_params = sum(p.numel() for p in self.policy.parameters())

    def reset(self) -> None:
        self.policy.reset()

    def make_noise(self, batch_size: int, seed: int) -> None:
        return None  # ACT is deterministic at inference

    @torch.inference_mode()
    def predict_chunk(
        self, obs: Observation, noise: Any = None, intervention: Any = None
    ) -> torch.Tensor:
        batch = {
            f"{IMAGE_PREFIX}agentview": obs.images["agentview"],
            OBS_STATE: obs.state,
        }
        return self.policy.predict_action_chunk(batch)


def _obs(image_size: int, state_dim: int, seed: int = 0) -> Observation:
    gen = torch.Generator().manual_seed(seed)
    return Observation(
        images={"agentview": torch.rand(1, 3, image_size, image_size, generator=gen)},
        state=torch.rand(1, state_dim, generator=gen),
        instruction=["pick up the red cube"],
    )


def measure(backbone: Any, obs: Observation, rounds: int, warmup: int = 3) -> dict[str, Any]:
    cfg = RefinerConfig(mode="E")
    single = IDRWrapper(backbone, RefinerConfig(mode="baseline"))
    batched = IDRWrapper(backbone, cfg, batched=True)
    sequential = IDRWrapper(backbone, cfg, batched=False)
    variants = {"single": single, "batched_3pass": batched, "sequential_3pass": sequential}
    times: dict[str, list[float]] = {k: [] for k in variants}
    for r in range(warmup + rounds):
        for name, pol in variants.items():
            t0 = time.perf_counter()
            pol.infer(obs, step_seed=r)
            if r >= warmup:
                times[name].append((time.perf_counter() - t0) * 1e3)
    med = {k: statistics.median(v) for k, v in times.items()}
    return {
        "median_ms": med,
        "p90_ms": {k: sorted(v)[int(0.9 * (len(v) - 1))] for k, v in times.items()},
        "ratio_batched_vs_single": med["batched_3pass"] / med["single"],
        "ratio_sequential_vs_single": med["sequential_3pass"] / med["single"],
        "rounds": rounds,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--out", type=Path, default=RESULTS)
    ap.add_argument("--skip-act", action="store_true")
    args = ap.parse_args()

    results: dict[str, Any] = {
        "machine": {
            **machine_record(),
            "python": platform.python_version(),
            "torch": torch.__version__,
            "threads": torch.get_num_threads(),
            "device": "cpu",
        },
        "backbones": {},
    }
    fake = FakeMarkerBackbone(chunk_len=4, noise_std=0.1)
    results["backbones"]["fake_marker"] = measure(fake, _obs(32, 2), args.rounds)
    tiny = Path(__file__).resolve().parents[1] / "checkpoints" / "tiny_vla"
    if tiny.is_dir():
        from workers.backbones.lerobot import LerobotBackbone

        bb = LerobotBackbone(
            str(tiny)
        )  # the real adapter: processors, state do() after the normalizer
        obs = Observation(
            images={c: torch.rand(1, 3, 96, 96) for c in bb.cameras},
            state=torch.rand(1, 8),
            instruction=["pick up the red cube"],
        )
        results["backbones"]["tiny_vla_lerobot_adapter"] = measure(bb, obs, args.rounds)
    if not args.skip_act:
        act = ACTBenchBackbone()
        r = measure(act, _obs(96, 8), args.rounds)
        r["params_millions"] = act.n_params / 1e6
        r["target_batched_ratio_max"] = 1.6
        results["backbones"]["lerobot_act_96px"] = r
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")

    print(
        f"{'backbone':<18} {'single ms':>10} {'batched ms':>11} {'seq ms':>9} {'batched/1':>10} {'seq/1':>7}"
    )
    for name, r in results["backbones"].items():
        m = r["median_ms"]
        print(
            f"{name:<18} {m['single']:>10.2f} {m['batched_3pass']:>11.2f} {m['sequential_3pass']:>9.2f} "
            f"{r['ratio_batched_vs_single']:>10.2f} {r['ratio_sequential_vs_single']:>7.2f}"
        )
    print(f"written to {args.out}")


if __name__ == "__main__":
    main()
