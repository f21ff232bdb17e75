"""``lerobot-idr-wrap BASE_DIR OUT_DIR [--mode E] [--tau T] ...``: an IDR folder around a lerobot
checkpoint, loadable by ``--policy.path=OUT_DIR`` in lerobot-eval, lerobot-rollout and the
async policy server (through ``lerobot-idr-policy-server``).

The folder holds config.json (type ``idr``: the base's path and the sha256 of its weights, IDR's
settings, the base's features) and the base's processors with IDR's two steps inserted; no
weights of its own (``--bundle`` copies the base into ``OUT_DIR/base`` for a robot computer).
Everything is checked before anything is written; the folder appears whole or not at all.
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

from idr_core.refiner import GUIDANCES, MODES

BUNDLED = "base"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="lerobot-idr-wrap",
        description="Wrap a lerobot policy checkpoint with IDR (policy type 'idr').",
    )
    p.add_argument("base_dir", type=Path, help="the base policy's checkpoint folder")
    p.add_argument("out_dir", type=Path, help="the IDR folder to make (--policy.path=OUT_DIR)")
    p.add_argument("--mode", default="E", choices=MODES, help="E: the full method (default)")
    p.add_argument("--tau", type=float, default=None, help="gate threshold (calibrate it)")
    p.add_argument("--alpha", type=float, default=0.08)
    p.add_argument("--beta", type=float, default=0.05)
    p.add_argument("--lam", type=float, default=0.1)
    p.add_argument("--eps", type=float, default=1e-6)
    p.add_argument("--guidance", default="visual", choices=GUIDANCES)
    p.add_argument("--w", type=float, default=0.08, help="mode cfg's guidance weight")
    p.add_argument("--samples", type=int, default=3, help="mode ensemble's draws")
    p.add_argument("--te-coeff", type=float, default=0.01, help="mode temporal's coefficient")
    p.add_argument("--strategy", default="zero", help="intervention: zero, mean, gaussian")
    p.add_argument(
        "--state-space",
        default="centered",
        help="do(S) about the dataset mean in physical units (centered), after the normalizer "
        "(normalized), or about the origin (raw)",
    )
    p.add_argument("--refine-space", default="physical", help="physical|normalized actions")
    p.add_argument("--n-action-steps", type=int, default=None, help="default: the base's")
    p.add_argument("--no-clip", action="store_true", help="do not clip into the base's bounds")
    p.add_argument("--deadline-ms", type=float, default=None)
    p.add_argument("--diagnostics-dir", default=None, help="the sidecar's folder")
    p.add_argument("--device", default="cpu", help="device written into the folder's config")
    p.add_argument("--bundle", action="store_true", help="copy the base into OUT_DIR/base")
    p.add_argument("--force", action="store_true", help="replace an existing OUT_DIR")
    return p


def wrap(args: argparse.Namespace) -> Path:
    """Make the IDR folder; raise ValueError (naming the field and the fix) before writing."""
    from idr_core.checkpoint import WEIGHTS, sha256_file

    from lerobot_policy_idr.configuration_idr import IDRConfig, read_base_config
    from lerobot_policy_idr.processor_idr import insert_idr_steps, load_base_processors

    base = args.base_dir.expanduser().resolve()
    out = args.out_dir.expanduser().resolve()
    if out.exists() and any(out.iterdir()) and not args.force:
        raise ValueError(f"OUT_DIR {out} exists and is not empty: choose another, or --force")
    if out == base or (base in out.parents and not args.bundle):
        raise ValueError(f"OUT_DIR {out} must not be inside BASE_DIR {base}")
    cfg = IDRConfig(
        base_policy_path=str(base),
        mode=args.mode,
        tau=args.tau,
        alpha=args.alpha,
        beta=args.beta,
        lam=args.lam,
        eps=args.eps,
        guidance=args.guidance,
        w=args.w,
        samples=args.samples,
        te_coeff=args.te_coeff,
        intervention_strategy=args.strategy,
        state_space=args.state_space,
        refine_space=args.refine_space,
        n_action_steps=args.n_action_steps,
        deadline_ms=args.deadline_ms,
        clip_actions=not args.no_clip,
        diagnostics_dir=args.diagnostics_dir,
        device=args.device,
    )
    cfg.resolve_base()  # exists, a supported lerobot checkpoint with complete weights
    cfg.copy_features(read_base_config(base))
    cfg.validate_features()
    cfg.base_weights_sha256 = sha256_file(base / WEIGHTS)
    pre, post = insert_idr_steps(*load_base_processors(base, args.device), cfg)

    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        if args.bundle:
            shutil.copytree(base, tmp / BUNDLED)
            cfg.base_policy_path = BUNDLED
        cfg._save_pretrained(tmp)
        pre.save_pretrained(tmp)
        post.save_pretrained(tmp)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        out = wrap(args)
    except ValueError as e:
        print(f"lerobot-idr-wrap: error: {e}", file=sys.stderr)
        return 2
    tau = "" if args.tau is None else f", tau={args.tau}"
    print(f"IDR folder {out} (mode {args.mode}{tau}) around {args.base_dir}")
    print(f"  lerobot-eval --policy.path={out} --env.type=...")
    return 0


if __name__ == "__main__":
    sys.exit(main())
