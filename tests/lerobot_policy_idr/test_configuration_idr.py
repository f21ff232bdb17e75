"""The ``idr`` config: registered with lerobot, round trip through config.json and lerobot's
CLI parser, and one clear refusal per bad input before any weight is loaded."""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass

import pytest
from lerobot.configs.policies import PreTrainedConfig
from lerobot_policy_idr.configuration_idr import IDRConfig, IDRConfigError

from tests.lerobot_policy_idr.conftest import make_idr


@dataclass
class PolicyArgs:
    """The ``--policy.*`` part of lerobot-eval's config, parsed by draccus as lerobot does."""

    policy: PreTrainedConfig | None = None


def test_idr_and_tiny_vla_are_registered_policy_types() -> None:
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class
    from lerobot_policy_idr.modeling_idr import IDRPolicy

    assert {"idr", "tiny_vla"} <= set(PreTrainedConfig.get_known_choices())
    assert get_policy_class("idr") is IDRPolicy  # lerobot's <X>Config -> modeling_<x>.<X>Policy
    assert get_policy_class("tiny_vla").__name__ == "TinyVLAPolicy"


def test_the_method_imports_without_lerobot_or_torch() -> None:
    import subprocess
    import sys

    code = (
        "import sys, idr_core.refiner, idr_core.interventions, idr_core.three_pass;"
        "import idr_core.features, idr_core.tensors;"
        "print(sorted(m for m in ('torch', 'lerobot') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


@pytest.mark.slow
def test_config_round_trips_through_its_folder_and_lerobots_parser(bases, tmp_path) -> None:
    import draccus

    folder = make_idr(
        bases["act"], tmp_path / "idr", "--mode", "C", "--tau", "2.5", "--alpha", "0.1"
    )
    cfg = PreTrainedConfig.from_pretrained(folder)
    assert isinstance(cfg, IDRConfig) and cfg.type == "idr"
    assert (cfg.mode, cfg.tau, cfg.alpha, cfg.beta) == ("C", 2.5, 0.1, 0.05)
    assert cfg.refiner().mode == "C" and cfg.refiner().tau == 2.5
    base_cfg = json.loads((bases["act"] / "config.json").read_text())
    assert set(cfg.input_features) == set(base_cfg["input_features"])
    # --policy.type=idr --policy.base_policy_path=... as lerobot's CLI parses it
    parsed = draccus.parse(
        PolicyArgs,
        args=[
            "--policy.type=idr",
            f"--policy.base_policy_path={bases['act']}",
            "--policy.mode=diagnose",
        ],
    ).policy
    assert isinstance(parsed, IDRConfig) and parsed.mode == "diagnose"
    assert set(parsed.input_features) == set(base_cfg["input_features"])  # read from the base
    assert parsed.resolve_base() == bases["act"]


@pytest.mark.parametrize(
    "fields, match",
    [
        ({"mode": "E"}, r"policy.mode='E' refines actions and needs policy.tau"),
        ({"mode": "Z"}, r"policy.mode='Z' is unknown"),
        ({"mode": "E", "tau": -1.0}, r"policy.tau=-1.0 must be a number >= 0"),
        ({"mode": "diagnose", "intervention_strategy": "blur"}, r"intervention_strategy='blur'"),
        ({"mode": "diagnose", "state_space": "pixel"}, r"policy.state_space='pixel' is unknown"),
        ({"mode": "diagnose", "refine_space": "joint"}, r"policy.refine_space='joint'"),
        ({"mode": "diagnose", "deadline_ms": 0.0}, r"policy.deadline_ms=0.0 must be > 0"),
    ],
)
def test_bad_settings_are_refused_naming_the_field(fields, match) -> None:
    with pytest.raises(IDRConfigError, match=match):
        IDRConfig(**fields)


@pytest.mark.slow
def test_bad_bases_are_refused_before_loading(bases, tmp_path) -> None:
    def refused(path, match):
        with pytest.raises(IDRConfigError, match=match):
            IDRConfig(mode="diagnose", base_policy_path=str(path)).resolve_base()

    refused(tmp_path / "nowhere", r"policy.base_policy_path=.*does not exist")
    (tmp_path / "empty").mkdir()
    refused(tmp_path / "empty", r"is not a lerobot policy: no config.json")
    with pytest.raises(IDRConfigError, match=r"base_policy_path is required"):
        IDRConfig(mode="diagnose").resolve_base()
    for kind, match in (
        ("groot", "processors from the hub"),
        ("tdmpc", "state-based RL planner"),
        ("pi0_fast", "FAST action tokenizer"),
    ):
        other = tmp_path / kind
        shutil.copytree(bases["act"], other)
        cfg = json.loads((other / "config.json").read_text())
        (other / "config.json").write_text(json.dumps({**cfg, "type": kind}))
        refused(
            other,
            rf"base type {kind!r} .*{match}.*act, diffusion, pi0, pi05, smolvla, xvla, vqbet, multi_task_dit, eo1, evo1",
        )
    for drop, what in (
        ("observation.state", "no observation.state"),
        ("observation.images.agentview", "no image"),
    ):
        blind = tmp_path / f"without_{drop}"
        shutil.copytree(bases["act"], blind)
        cfg = json.loads((blind / "config.json").read_text())
        del cfg["input_features"][drop]
        (blind / "config.json").write_text(json.dumps(cfg))
        refused(blind, rf"the base reads {what} .*--policy.mode=baseline")
        IDRConfig(mode="baseline", base_policy_path=str(blind)).resolve_base()  # no intervention
    typo = tmp_path / "typo"
    shutil.copytree(bases["act"], typo)
    cfg = json.loads((typo / "config.json").read_text())
    (typo / "config.json").write_text(json.dumps({**cfg, "type": "acts"}))
    refused(typo, r"base type 'acts' \(did you mean act\b.*\?\) is not supported")
    truncated = tmp_path / "truncated"
    shutil.copytree(bases["act"], truncated)
    weights = truncated / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])
    refused(truncated, r"not a complete safetensors file")


@pytest.mark.slow
def test_a_method_the_base_cannot_run_is_refused_before_loading(bases, tmp_path) -> None:
    """idr-eval's pre-flight rule (``idr_core.methods.refusal``), from the config: ensemble on a
    deterministic base, temporal on one executed action, pcd in lerobot's tools; one message
    naming the method, the base and why, and no folder written. What runs needs no
    counterfactual step in the preprocessor."""
    from lerobot_policy_idr.wrap import main as wrap_main

    def refused(match: str, **fields) -> None:
        with pytest.raises(IDRConfigError, match=match):
            IDRConfig(base_policy_path=str(bases["act"]), **fields).resolve_base()

    refused(r"policy.mode='ensemble': mode 'ensemble' .*act.* is deterministic", mode="ensemble")
    refused(
        r"policy.mode='temporal': mode 'temporal' .*one action per inference",
        mode="temporal",
        n_action_steps=1,
    )
    with pytest.raises(IDRConfigError, match=r"policy.mode='pcd': .*on a robot"):
        IDRConfig(mode="pcd")
    assert wrap_main([str(bases["act"]), str(tmp_path / "no"), "--mode", "ensemble"]) == 2
    assert not (tmp_path / "no").exists()
    for kind, mode in (("act", "temporal"), ("diffusion", "ensemble")):
        folder = make_idr(bases[kind], tmp_path / mode, "--mode", mode, "--samples", "4")
        assert "idr_" not in (folder / "policy_preprocessor.json").read_text()
        cfg = PreTrainedConfig.from_pretrained(folder)
        assert (cfg.mode, cfg.refiner().samples) == (mode, 4)
