"""The plugin installs on a robot computer next to lerobot alone: a fresh venv with lerobot
0.6.1 and ``pip install ./lerobot_policy_idr`` (no Ray, MLflow, simulator or idr-eval), where
lerobot's factory loads the shipped tiny VLA checkpoint (its type is registered by the plugin)
and an IDR folder wrapped around it infers."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[2]

PROBE = """
import importlib.util, json, sys
import torch
import lerobot_policy_idr
from lerobot.configs.policies import PreTrainedConfig
from lerobot.policies.factory import get_policy_class, make_pre_post_processors
absent = [m for m in ("ray", "mlflow", "mujoco", "robosuite", "pipeline", "workers")
          if importlib.util.find_spec(m)]
folder = sys.argv[1]
cfg = PreTrainedConfig.from_pretrained(folder)
cfg.pretrained_path = folder
policy = get_policy_class(cfg.type).from_pretrained(folder, config=cfg)
pre, post = make_pre_post_processors(cfg, pretrained_path=folder)
obs = {k: torch.rand(1, *f.shape) for k, f in cfg.input_features.items()}
obs["task"] = ["pick up the red cube"]
with torch.inference_mode():
    chunk = post(policy.predict_action_chunk(pre(obs)))
policy.sidecar.flush()
print(json.dumps({"present": absent, "base": policy.base.config.type, "shape": list(chunk.shape)}))
"""


def test_the_plugin_installs_and_runs_in_a_venv_with_only_lerobot(tmp_path) -> None:
    uv = Path(sys.executable).parent / "uv"
    assert uv.exists(), "make setup installs uv into .venv"
    venv = tmp_path / "robot-venv"
    subprocess.run([str(uv), "venv", "-q", "--python", sys.executable, str(venv)], check=True)
    pkg = tmp_path / "lerobot_policy_idr"  # a copy: no editable link back into the checkout
    shutil.copytree(ROOT / "lerobot_policy_idr", pkg, ignore=shutil.ignore_patterns("*.egg-info"))
    install = subprocess.run(
        [
            str(uv),
            "pip",
            "install",
            "-q",
            "--python",
            str(venv / "bin" / "python"),
            "-c",
            str(ROOT / "requirements.lock"),
            "lerobot==0.6.1",
            str(pkg),
        ],
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert install.returncode == 0, install.stderr[-2000:]
    folder, diag = tmp_path / "idr_tiny", tmp_path / "diag"
    wrap = subprocess.run(
        [
            str(venv / "bin" / "lerobot-idr-wrap"),
            str(ROOT / "checkpoints" / "tiny_vla"),
            str(folder),
            "--mode",
            "diagnose",
            "--diagnostics-dir",
            str(diag),
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert wrap.returncode == 0, wrap.stderr[-2000:]
    probe = subprocess.run(
        [str(venv / "bin" / "python"), "-c", PROBE, str(folder)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=300,
    )
    assert probe.returncode == 0, probe.stderr[-2000:]
    import json

    out = json.loads(probe.stdout.strip().splitlines()[-1])
    assert out == {"present": [], "base": "tiny_vla", "shape": [1, 8, 7]}
    assert list(diag.glob("part-*.parquet"))
