"""The zoo's sub-model files: installed into a Hugging Face cache in its own layout, found there
by hub id from any working directory, offline; SmolVLM's image tokens where SmolVLA reads them."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from training import zoo_hub

PROBE = """
import sys
from transformers import AutoConfig, AutoProcessor, AutoTokenizer
cache = sys.argv[1]
tok = AutoTokenizer.from_pretrained("idr-eval/zoo-xvla-tokenizer", cache_dir=cache)
print("xvla", tok("pick up the red cube")["input_ids"][0], len(tok))
proc = AutoProcessor.from_pretrained("idr-eval/zoo-smolvlm2-tiny", cache_dir=cache)
cfg = AutoConfig.from_pretrained("idr-eval/zoo-smolvlm2-tiny", cache_dir=cache)
t = proc.tokenizer
print("smol", t.fake_image_token_id, t.global_image_token_id, cfg.image_token_id,
      t.convert_tokens_to_ids("<image>"), cfg.text_config.vocab_size, len(t))
"""


def test_installed_files_load_by_hub_id_offline_from_another_folder(tmp_path: Path) -> None:
    cache = tmp_path / "hub"
    ids = zoo_hub.install(cache)
    assert ids == ["idr-eval/zoo-smolvlm2-tiny", "idr-eval/zoo-xvla-tokenizer"]
    assert zoo_hub.install(cache) == ids  # idempotent: the same revisions
    for name in ("zoo-smolvlm2-tiny", "zoo-xvla-tokenizer"):
        repo = cache / f"models--idr-eval--{name}"
        rev = (repo / "refs" / "main").read_text()
        assert rev == zoo_hub._revision(zoo_hub.HUB_DIR / name)
        assert (repo / "snapshots" / rev / "tokenizer.json").is_file()
    run = subprocess.run(
        [sys.executable, "-c", PROBE, str(cache)],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={**os.environ, "HF_HUB_OFFLINE": "1"},
    )
    assert run.returncode == 0, run.stderr[-3000:]
    lines = dict(line.split(" ", 1) for line in run.stdout.splitlines())
    bos, n_xvla = map(int, lines["xvla"].split())
    assert bos == 2 and n_xvla < zoo_hub.XVLA_VOCAB  # <bos> first; ids below the image token
    fake, glob, image_cfg, image_tok, vocab, n_smol = map(int, lines["smol"].split())
    assert image_cfg == image_tok  # the model's image token is the tokenizer's <image>
    assert len({fake, glob, image_tok}) == 3 and max(fake, glob, image_tok) < vocab
    assert n_smol <= vocab


def test_the_florence_config_fits_two_96px_cameras_and_the_instruction() -> None:
    cfg = zoo_hub.xvla_florence_config()
    vision = cfg["vision_config"]
    side = 96
    for stride in vision["patch_stride"]:
        side //= stride
    assert side == 6 and side <= vision["max_position_embeddings"]
    tokens = 2 * side * side + 16  # both cameras + tokenizer_max_length
    assert tokens <= cfg["text_config"]["max_position_embeddings"]
    assert cfg["image_token_id"] == zoo_hub.XVLA_VOCAB - 1
