"""Offline does not depend on import order: in a process that imported huggingface_hub (and
datasets) before idr-eval, without any HF_* variable, the flags those libraries read are on
during ``evaluate``'s work and are given back afterwards."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[3]

SCRIPT = """
import json, os, sys
import huggingface_hub, huggingface_hub.constants as hub_constants
import datasets.config as ds_config
assert not hub_constants.HF_HUB_OFFLINE and not huggingface_hub.is_offline_mode()
from pipeline.api import evaluate
from pipeline.execution import runner

seen = {}
real = runner.run_episodes

def watching(*args, **kwargs):  # the episodes' work, as the runner calls it
    seen["during"] = {
        "hub_constant": hub_constants.HF_HUB_OFFLINE,
        "hub_is_offline_mode": huggingface_hub.is_offline_mode(),
        "datasets_hub": ds_config.HF_HUB_OFFLINE,
        "datasets_offline": ds_config.HF_DATASETS_OFFLINE,
        "env": {k: os.environ.get(k) for k in
                ("HF_HUB_OFFLINE", "HF_DATASETS_OFFLINE", "TRANSFORMERS_OFFLINE")},
    }
    return real(*args, **kwargs)

runner.run_episodes = watching
result = evaluate("conf/smoke.yaml", out=sys.argv[1],
                  overrides=["executor.kind=inline", "tracking.enabled=false"])
seen["stored"] = result.summary.stored
seen["after"] = {
    "hub_constant": hub_constants.HF_HUB_OFFLINE,
    "env": [k for k in ("HF_HUB_OFFLINE", "HF_DATASETS_OFFLINE", "TRANSFORMERS_OFFLINE")
            if k in os.environ],
}
print(json.dumps(seen))
"""


def _run(tmp_path: Path, env: dict[str, str]) -> dict:
    r = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tmp_path / "run")],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


def _clean_env() -> dict[str, str]:
    return {
        k: v
        for k, v in os.environ.items()
        if k not in ("HF_HUB_OFFLINE", "HF_DATASETS_OFFLINE", "TRANSFORMERS_OFFLINE")
    }


def test_evaluate_is_offline_when_huggingface_hub_was_imported_first(tmp_path: Path) -> None:
    seen = _run(tmp_path, _clean_env())
    assert seen["stored"] == 12
    during = seen["during"]
    assert during["hub_constant"] is True and during["hub_is_offline_mode"] is True
    assert during["datasets_hub"] is True and during["datasets_offline"] is True
    # child processes (a local Ray's actors, an env server) read the variables
    assert set(during["env"].values()) == {"1"}
    # given back: the training process may download again after the evaluation
    assert seen["after"] == {"hub_constant": False, "env": []}


def test_a_users_own_setting_stands(tmp_path: Path) -> None:
    seen = _run(tmp_path, {**_clean_env(), "HF_HUB_OFFLINE": "0"})
    assert seen["during"]["env"]["HF_HUB_OFFLINE"] == "0"
    assert seen["during"]["hub_constant"] is False  # HF_HUB_OFFLINE=0 allows downloads
