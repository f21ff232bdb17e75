"""A checkpoint carried through a channel with a per-file limit: float16 parts, restored as
float32 that lerobot's factory loads, with the rounding's effect on actions measured."""

from __future__ import annotations

import json
import shutil

import pytest
import torch
from safetensors.torch import load_file

from training import zoo_benchmarks
from training.zoo_carry import pack, unpack

SHIPPED = zoo_benchmarks.ROOT / "checkpoints" / "zoo" / "tiny_vla"


@pytest.mark.slow
def test_a_checkpoint_packed_in_parts_comes_back_as_float32_at_float16_precision(
    synthetic_tabletop, tmp_path, monkeypatch
) -> None:
    monkeypatch.setattr("training.zoo_carry.PART_BYTES", 200_000)  # several parts from 1 MB
    src = tmp_path / "tiny_vla"
    shutil.copytree(SHIPPED, src)
    parts = pack(src, tmp_path / "out", synthetic_tabletop, frames=6)
    assert len(parts) > 2 and all(p.stat().st_size <= 200_000 for p in parts)
    assert sum(p.stat().st_size for p in parts) < 0.7 * (src / "model.safetensors").stat().st_size

    dest = unpack(list(reversed(parts)), tmp_path / "back" / "tiny_vla")  # any order
    full, back = load_file(src / "model.safetensors"), load_file(dest / "model.safetensors")
    assert full.keys() == back.keys()
    for k, v in full.items():
        assert back[k].dtype == v.dtype
        if v.dtype == torch.float32:
            assert torch.equal(back[k], v.half().float())  # exactly the float16 rounding
    carried = json.loads((dest / "train_meta.json").read_text())["carried"]
    assert carried["weights_dtype"] == "float16" and carried["frames"] == 6
    assert 0 < carried["max_abs_action_diff_in_std"] < 0.05
    assert not (dest / "carry.json").exists()

    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class

    import lerobot_policy_idr  # noqa: F401  (registers tiny_vla)

    cfg = PreTrainedConfig.from_pretrained(dest)
    policy = get_policy_class(cfg.type).from_pretrained(dest, config=cfg)
    assert next(policy.parameters()).dtype == torch.float32
