"""The zoo's tabletop dataset with some state dims left out, for architectures that cannot mask
them.

The tabletop state's orientation dims (3-5: the end effector's axis-angle) move by a few
milliradians with each commanded motion, so a net fed them can read the last action off them
and copy it (the copycat shortcut, docs/tiny-vla.md): such a policy predicts the demonstrations'
actions well open-loop and drifts away closed-loop. The tiny VLA masks them with a flag
(``ignored_state_dims``); lerobot's ACT, Diffusion, X-VLA and SmolVLA have no such flag. This
writes a copy of a LeRobotDataset whose ``observation.state`` keeps only the given dims (every
other column, the videos or images, the episodes and the tasks as they are), with its info and
its stats (per dataset and per episode) cut to match; the tabletop suite's ``state_dims`` param
gives a policy the same dims at evaluation.

    python -m training.zoo_state --src data/zoo/tabletop --dst data/zoo/tabletop_pos --keep 0,1,2,6,7
"""

from __future__ import annotations

import argparse
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from idr_core.features import OBS_STATE


def _cut_column(table: pa.Table, name: str, keep: list[int]) -> pa.Table:
    values = np.asarray(table.column(name).to_pylist(), dtype=np.float32)[:, keep]
    arr = pa.FixedSizeListArray.from_arrays(pa.array(values.reshape(-1), pa.float32()), len(keep))
    return table.set_column(table.schema.get_field_index(name), name, arr)


def _cut_hf_metadata(schema: pa.Schema, n: int) -> dict[bytes, bytes]:
    meta = dict(schema.metadata or {})
    if b"huggingface" in meta:
        hf = json.loads(meta[b"huggingface"])
        hf["info"]["features"][OBS_STATE]["length"] = n
        meta[b"huggingface"] = json.dumps(hf).encode()
    return meta


def derive(src: Path, dst: Path, keep: list[int]) -> Path:
    info = json.loads((src / "meta" / "info.json").read_text())
    n_src = info["features"][OBS_STATE]["shape"][0]
    if not keep or any(not 0 <= k < n_src for k in keep) or len(set(keep)) != len(keep):
        raise SystemExit(f"--keep {keep}: distinct dims of the {n_src}-d state of {src}")
    if dst.exists():
        raise SystemExit(f"--dst {dst} exists; remove it first")
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("*.parquet"))
    for f in sorted(src.rglob("*.parquet")):
        out = dst / f.relative_to(src)
        out.parent.mkdir(parents=True, exist_ok=True)
        table = pq.read_table(f)
        if OBS_STATE in table.column_names:
            table = _cut_column(table, OBS_STATE, keep)
        for col in [c for c in table.column_names if c.startswith(f"stats/{OBS_STATE}/")]:
            if col.endswith("/count"):
                continue
            table = _cut_column(table, col, keep)
        table = table.replace_schema_metadata(_cut_hf_metadata(table.schema, len(keep)))
        pq.write_table(table, out)
    feat = info["features"][OBS_STATE]
    feat["shape"] = [len(keep)]
    if feat.get("names"):
        feat["names"] = [feat["names"][k] for k in keep]
    (dst / "meta" / "info.json").write_text(json.dumps(info, indent=4))
    stats = json.loads((src / "meta" / "stats.json").read_text())
    for key, value in stats[OBS_STATE].items():
        if key != "count" and isinstance(value, list) and len(value) == n_src:
            stats[OBS_STATE][key] = [value[k] for k in keep]
    (dst / "meta" / "stats.json").write_text(json.dumps(stats, indent=4))
    (dst / "meta" / "zoo_state.json").write_text(
        json.dumps({"source": str(src), "kept_state_dims": keep}, indent=2) + "\n"
    )
    return dst


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--src", type=Path, default=Path("data/zoo/tabletop"))
    ap.add_argument("--dst", type=Path, default=Path("data/zoo/tabletop_pos"))
    ap.add_argument("--keep", default="0,1,2,6,7", help="state dims to keep (comma-separated)")
    args = ap.parse_args(argv)
    derive(args.src, args.dst, [int(k) for k in args.keep.split(",")])
    print(f"wrote {args.dst}")


if __name__ == "__main__":
    main()
