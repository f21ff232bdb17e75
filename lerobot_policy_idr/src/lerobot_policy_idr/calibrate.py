"""``lerobot-idr-calibrate IDR_DIR SIDECAR_DIR [...] [--mode E]``: tau by the paper's rule.

The paper sets the gate threshold tau to the mean E_img of the baseline: run the IDR folder
in mode ``diagnose`` (three passes, the base action executed, E_img recorded) for a few
rollouts, then give their sidecar folders here; tau is written into the folder's config.json
(and ``--mode`` with it, to switch the folder to a refining mode).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from idr_core.refiner import MODES


def calibrate(
    idr_dir: Path, sidecars: list[Path], mode: str | None = None, rule: str = "calibrated"
) -> dict:
    """Compute tau from the sidecars' diagnose rows by ``rule`` (idr_core.calibration: the
    paper's mean E_img, a multiple or a percentile of it, as idr-eval's ``tau:`` spells it) and
    write it (and ``mode``) into ``idr_dir/config.json``; returns what was computed. Raises
    ValueError before writing."""
    from idr_core.calibration import TauSpec, parse_tau
    from idr_core.sidecar import read_sidecar

    spec = parse_tau(rule)
    if not isinstance(spec, TauSpec):
        raise ValueError(f"--rule {rule!r} is a number: set it with --policy.tau instead")

    cfg_path = idr_dir / "config.json"
    try:
        cfg = json.loads(cfg_path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"IDR_DIR {idr_dir}: no readable config.json ({e})") from None
    if cfg.get("type") != "idr":
        raise ValueError(f"IDR_DIR {idr_dir} is a {cfg.get('type')!r} folder, not an idr one")
    if mode is not None and mode not in MODES:
        raise ValueError(f"--mode {mode!r} is unknown; use one of {MODES}")
    frames = []
    for d in sidecars:
        try:
            frames.append(read_sidecar(d))
        except FileNotFoundError as e:
            raise ValueError(str(e)) from None
    import pandas as pd

    rows = pd.concat(frames, ignore_index=True)
    rows = rows[rows["mode"] == "diagnose"]
    e_img = rows["e_img"].dropna().astype(float)
    if e_img.empty:
        raise ValueError(
            "the sidecars hold no rows of mode 'diagnose': roll out with --policy.mode=diagnose "
            "(or an IDR folder made with --mode diagnose) first"
        )
    tau = spec.resolve(e_img.to_numpy())
    if not math.isfinite(tau):
        raise ValueError(f"{spec.text} of E_img is {tau}: the diagnose rows are not finite")
    cfg["tau"] = tau
    if mode is not None:
        cfg["mode"] = mode
    tmp = cfg_path.with_name(".config.json.tmp")
    tmp.write_text(json.dumps(cfg, indent=4))
    os.replace(tmp, cfg_path)
    return {
        "tau": tau,
        "inferences": len(e_img),
        "episodes": int(rows[["episode"]].drop_duplicates().shape[0]),
        "e_img_std": float(e_img.std(ddof=0)),
        "mode": cfg["mode"],
        "rule": spec.text,
    }


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="lerobot-idr-calibrate",
        description="Set an IDR folder's tau to the mean E_img of diagnose rollouts.",
    )
    p.add_argument("idr_dir", type=Path)
    p.add_argument("sidecars", type=Path, nargs="+", help="diagnostics folders of the rollouts")
    p.add_argument("--mode", default=None, help="also switch the folder to this mode (e.g. E)")
    p.add_argument(
        "--rule",
        default="calibrated",
        help="calibrated (the mean E_img, the paper's rule; default), calibrated*K, "
        "calibrated_qP, or both: the same statistic as idr-eval's tau",
    )
    args = p.parse_args(argv)
    try:
        out = calibrate(args.idr_dir, args.sidecars, args.mode, args.rule)
    except ValueError as e:
        print(f"lerobot-idr-calibrate: error: {e}", file=sys.stderr)
        return 2
    print(
        f"tau = {out['tau']:.6g} (mean E_img over {out['inferences']} inferences, std "
        f"{out['e_img_std']:.3g}); written to {args.idr_dir / 'config.json'} (mode {out['mode']})"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
