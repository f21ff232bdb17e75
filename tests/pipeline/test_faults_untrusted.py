"""Fault 7, untrusted inputs: no pickle is ever loaded (weights from safetensors only, LIBERO's
init states through ``torch.load(weights_only=True)``), a RUN_DIR that ``..`` or a symlink
leads out of the output root is refused, and the MLflow UI binds to 127.0.0.1 unless asked."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest

from pipeline import cli
from pipeline.execution.runner import plan_run
from pipeline.planning.config import ConfigError, load_config
from workers.safe_load import load_numpy_array

ROOT = Path(__file__).resolve().parents[2]
UNSAFE = {
    r"\bpickle\.loads?\(": "pickle.load",
    r"\b(cloudpickle|dill|shelve|marshal)\b": "a pickle-like loader",
    r"\bjoblib\.load\(": "joblib.load",
    r"\byaml\.(load|unsafe_load|full_load)\(": "yaml.load without SafeLoader",
    r"allow_pickle\s*=\s*True": "np.load(allow_pickle=True)",
}


def test_no_code_loads_pickles() -> None:
    found = []
    for folder in ("pipeline", "workers", "benchmarks", "scripts"):
        for f in (ROOT / folder).rglob("*.py"):
            text = f.read_text()
            for pattern, what in UNSAFE.items():
                if re.search(pattern, text):
                    found.append(f"{f.relative_to(ROOT)}: {what}")
            for call in re.finditer(r"torch\.load\(([^()]|\([^()]*\))*\)", text):
                if "weights_only=True" not in call.group(0):
                    found.append(f"{f.relative_to(ROOT)}: {call.group(0)}")
    assert not found, found


class _Exploit:
    def __reduce__(self):
        return (Path.touch, (Path(self.marker),))


def test_init_states_load_without_pickle(tmp_path) -> None:
    import torch

    files = sorted(Path(sys.prefix).glob("lib/python3*/site-packages/libero/**/*.pruned_init"))
    if not files:
        pytest.skip("hf-libero is not installed")
    for f in files[:3]:
        np.testing.assert_array_equal(load_numpy_array(f), torch.load(f, weights_only=False))
    exploit = _Exploit()
    exploit.marker = str(tmp_path / "pwned")
    torch.save(exploit, tmp_path / "evil.pruned_init")
    with pytest.raises(ValueError, match="refused, it is not a plain array file"):
        load_numpy_array(tmp_path / "evil.pruned_init")
    assert not (tmp_path / "pwned").exists()


def test_pickled_checkpoint_is_refused_before_work(tmp_path, capsys) -> None:
    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    (ckpt / "config.json").write_text(json.dumps({"type": "act"}))
    (ckpt / "pytorch_model.bin").write_bytes(b"\x80\x04pickle")
    args = ["run", str(ROOT / "conf/smoke.yaml"), "--out", str(tmp_path / "run")]
    code = cli.main([*args, "backbone.kind=lerobot", f"backbone.params={{path: {ckpt}}}"])
    err = capsys.readouterr().err
    assert code == 2 and "backbone.params.path" in err and "pickled weights are refused" in err
    assert not (tmp_path / "run").exists()


@pytest.fixture
def roots(tmp_path):
    root, outside = tmp_path / "runs", tmp_path / "elsewhere"
    root.mkdir()
    outside.mkdir()
    (root / "link").symlink_to(outside)
    (tmp_path / "link_out").symlink_to(outside)
    return root, outside


@pytest.mark.parametrize(
    ("out", "pattern"),
    [
        ("runs/../elsewhere/run", r"its '\.\.' leads to .*elsewhere/run, outside the output root"),
        ("runs/link/run", r"the symlink .*runs/link -> .*elsewhere leads outside the output root"),
        ("link_out/run", r"the symlink .*link_out -> .*elsewhere leads outside the output root"),
        # '..' after a symlink climbs from the link's target, not from runs/
        ("runs/link/../run", r"its '\.\.' leads to .*/run, outside the output root"),
    ],
)
def test_run_dir_escaping_the_output_root_is_refused(tmp_path, roots, out, pattern) -> None:
    root, _ = roots
    cfg = load_config(ROOT / "conf/smoke.yaml", [f"output_root={root}"])
    with pytest.raises(ConfigError, match=pattern):
        plan_run(cfg, tmp_path / out)


@pytest.mark.parametrize("out", ["runs/a/../b", "plain/run"])
def test_run_dirs_that_stay_put_are_allowed(tmp_path, roots, out) -> None:
    root, _ = roots
    cfg = load_config(ROOT / "conf/smoke.yaml", [f"output_root={root}"])
    assert plan_run(cfg, tmp_path / out).specs


def test_config_name_cannot_escape_the_output_root(tmp_path, capsys, fault_log) -> None:
    code = cli.main(["run", str(ROOT / "conf/smoke.yaml"), f"output_root={tmp_path}", "name=../x"])
    err = capsys.readouterr().err
    assert code == 2 and "name: '../x' must be one path component" in err
    assert not (tmp_path.parent / "x").exists()
    fault_log.record(
        "untrusted paths and checkpoints",
        "RUN_DIR with '..' or symlinks out of output_root; name=../x; a pickled checkpoint; a "
        "pickle exploit as LIBERO init states",
        "refused before any work, one error naming the field; no pickle is ever loaded",
        {"refused": True, "files_written": 0},
    )
