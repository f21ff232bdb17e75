"""The zoo's sub-model files (tokenizers, VLM configs), shipped in the repo, loaded by hub id.

X-VLA and SmolVLA name a tokenizer or a VLM by a string that lerobot hands to transformers'
``from_pretrained`` (``tokenizer_name``, ``vlm_model_name``), inside the policy's constructor and
its processor. A path there would be resolved against the working directory, so a checkpoint
saved with one would load only from the folder it was trained in. The zoo therefore names them
by hub ids (``idr-eval/zoo-...``) and ships their files under ``checkpoints/zoo/hub/``;
``install()`` (run by ``make setup``) puts them into the local Hugging Face cache in the cache's
own layout, where transformers finds them offline from any working directory, in lerobot-eval
and in the harness alike. Nothing is downloaded: the hub ids do not exist on the hub.

    python -m training.zoo_hub build     # write the files from the zoo dataset's instructions
    python -m training.zoo_hub install   # copy them into the HF cache (idempotent)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
from pathlib import Path

from training.zoo_data import dataset_tasks

ROOT = Path(__file__).resolve().parents[1]
HUB_DIR = ROOT / "checkpoints" / "zoo" / "hub"
ORG = "idr-eval"
XVLA_TOKENIZER = "zoo-xvla-tokenizer"
SMOLVLM = "zoo-smolvlm2-tiny"
# special tokens first, so their ids (0-3) are the ones xvla_florence_config() names
SPECIAL = ("<pad>", "<eos>", "<bos>", "<unk>")
XVLA_VOCAB = 128  # embedding rows; the tokenizer's ids fit below, the image token takes the last


def repo_id(name: str) -> str:
    return f"{ORG}/{name}"


# SmolVLM's image tokens, as its processor and SmolVLA read them off the tokenizer
SMOLVLM_EXTRA = {
    "image_token": "<image>",
    "fake_image_token": "<fake_token_around_image>",
    "global_image_token": "<global-img>",
    "end_of_utterance_token": "<end_of_utterance>",
}


def build_word_tokenizer(
    out: Path, instructions: list[str], extra: dict[str, str] | None = None
) -> Path:
    """A word-level tokenizer trained on ``instructions`` (with a leading <bos>); ``extra``:
    named special tokens (``fake_image_token`` -> ``tokenizer.fake_image_token_id``)."""
    from tokenizers import Tokenizer, models, pre_tokenizers, processors, trainers
    from transformers import PreTrainedTokenizerFast

    tok = Tokenizer(models.WordLevel(unk_token="<unk>"))
    tok.pre_tokenizer = pre_tokenizers.Whitespace()
    tok.train_from_iterator(
        [s.lower() for s in instructions],
        trainers.WordLevelTrainer(special_tokens=[*SPECIAL, *(extra or {}).values()]),
    )
    tok.post_processor = processors.TemplateProcessing(
        single="<bos> $A", pair="<bos> $A $B", special_tokens=[("<bos>", 2)]
    )
    if tok.get_vocab_size() >= XVLA_VOCAB:
        raise SystemExit(
            f"{len(instructions)} instructions give {tok.get_vocab_size()} words; the zoo's "
            f"X-VLA embeds {XVLA_VOCAB - 1}: raise XVLA_VOCAB in training/zoo_hub.py"
        )
    fast = PreTrainedTokenizerFast(
        tokenizer_object=tok,
        pad_token="<pad>",
        eos_token="<eos>",
        bos_token="<bos>",
        unk_token="<unk>",
        model_max_length=64,
        **({"extra_special_tokens": dict(extra)} if extra else {}),
    )
    out.mkdir(parents=True, exist_ok=True)
    fast.save_pretrained(out)
    # transformers' AutoTokenizer reads a model config first; from the cache a missing one is an
    # error (from a folder it is not), so an empty one stands in
    (out / "config.json").write_text("{}\n")
    return out


def xvla_florence_config() -> dict:
    """Florence-2 at small widths for the zoo's X-VLA: DaViT in three stages (strides 4, 2, 2:
    a 96 px camera becomes 6 x 6 tokens), a one-layer BART over the instruction and the image
    tokens of both cameras."""
    return {
        "vision_config": {
            "model_type": "florence_vision",
            "depths": [1, 1, 1],
            "patch_size": [7, 3, 3],
            "patch_stride": [4, 2, 2],
            "patch_padding": [3, 1, 1],
            "patch_prenorm": [False, True, True],
            "embed_dim": [32, 64, 96],
            "num_heads": [2, 4, 6],
            "num_groups": [2, 4, 6],
            "window_size": 6,
            "drop_path_rate": 0.0,
            "projection_dim": 64,
            "max_position_embeddings": 16,
            "max_temporal_embeddings": 4,
        },
        "text_config": {
            "model_type": "bart",
            "vocab_size": XVLA_VOCAB,
            "d_model": 64,
            "encoder_layers": 1,
            "decoder_layers": 1,
            "encoder_attention_heads": 2,
            "decoder_attention_heads": 2,
            "encoder_ffn_dim": 128,
            "decoder_ffn_dim": 128,
            "max_position_embeddings": 128,
        },
        "image_token_id": XVLA_VOCAB - 1,
        "pad_token_id": 0,
        "bos_token_id": 2,
        "eos_token_id": 1,
    }


def build_smolvlm(out: Path, instructions: list[str]) -> Path:
    """SmolVLM2's config and processor at small widths (no weights: SmolVLA builds the VLM from
    the config with ``load_vlm_weights=false``): a 2-layer SigLIP-like vision tower of width 64
    on 96 px images in 8 px patches (12 x 12, pixel-shuffled to 6 x 6 = 36 tokens per camera)
    and a 4-layer Llama of width 64 over the word-level tokenizer."""
    from transformers import SmolVLMConfig, SmolVLMImageProcessor, SmolVLMProcessor
    from transformers.models.smolvlm.video_processing_smolvlm import SmolVLMVideoProcessor

    build_word_tokenizer(out, instructions, SMOLVLM_EXTRA)
    from transformers import AutoTokenizer

    tok = AutoTokenizer.from_pretrained(out)
    cfg = SmolVLMConfig(
        vision_config={
            "hidden_size": 64,
            "intermediate_size": 128,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "image_size": 96,
            "patch_size": 8,
        },
        text_config={
            "model_type": "llama",
            "hidden_size": 64,
            "intermediate_size": 128,
            "num_hidden_layers": 4,
            "num_attention_heads": 4,
            "num_key_value_heads": 2,
            "head_dim": 16,
            "vocab_size": XVLA_VOCAB,
            "max_position_embeddings": 512,
            "pad_token_id": 0,
            "rms_norm_eps": 1e-5,
        },
        scale_factor=2,
        image_token_id=tok.convert_tokens_to_ids(SMOLVLM_EXTRA["image_token"]),
        pad_token_id=0,
    )
    cfg.save_pretrained(out)
    size = {"longest_edge": 96}
    SmolVLMProcessor(
        image_processor=SmolVLMImageProcessor(size=size, max_image_size=size),
        tokenizer=tok,
        video_processor=SmolVLMVideoProcessor(size=size, max_image_size=size),
        image_seq_len=36,
    ).save_pretrained(out)
    return out


def build(dataset: Path) -> None:
    tasks = dataset_tasks(dataset)
    build_word_tokenizer(HUB_DIR / XVLA_TOKENIZER, tasks)
    build_smolvlm(HUB_DIR / SMOLVLM, tasks)
    print(f"wrote {HUB_DIR / XVLA_TOKENIZER} and {HUB_DIR / SMOLVLM}")


def _revision(folder: Path) -> str:
    h = hashlib.sha1()
    for f in sorted(p for p in folder.rglob("*") if p.is_file()):
        h.update(f.relative_to(folder).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()


def install(cache: Path | None = None, hub_dir: Path = HUB_DIR) -> list[str]:
    """Copy every folder of ``hub_dir`` into the HF cache as ``idr-eval/<folder>`` (the cache's
    ``models--org--name/{refs/main,snapshots/<rev>}`` layout). Returns the ids installed."""
    from huggingface_hub import constants

    cache = Path(cache or constants.HF_HUB_CACHE)
    done = []
    for folder in sorted(p for p in hub_dir.iterdir() if p.is_dir()) if hub_dir.is_dir() else []:
        rev = _revision(folder)
        repo = cache / f"models--{ORG}--{folder.name}"
        snap = repo / "snapshots" / rev
        if not snap.is_dir():
            shutil.copytree(folder, snap)
        (repo / "refs").mkdir(parents=True, exist_ok=True)
        (repo / "refs" / "main").write_text(rev)
        done.append(repo_id(folder.name))
    return done


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="verb", required=True)
    b = sub.add_parser("build", help="write the sub-model files under checkpoints/zoo/hub")
    b.add_argument("--dataset", type=Path, default=ROOT / "data" / "zoo" / "tabletop")
    i = sub.add_parser("install", help="put them into the local Hugging Face cache")
    i.add_argument("--cache", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.verb == "build":
        build(args.dataset)
    else:
        print(json.dumps(install(args.cache)))


if __name__ == "__main__":
    main()
