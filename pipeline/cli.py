"""``idr-eval``: run a config, rebuild a report, compare runs, open the MLflow UI."""

from __future__ import annotations

import argparse
import os
import sys

# Arrow's buffers from the system allocator, which hands large freed blocks back to the OS at
# once; Arrow's default (mimalloc) keeps them: a report over 5 M step rows peaked at 2.3-2.6 GB
# with it, 2.0 GB without (benchmarks/bench_report_scale.py). Read by Arrow when it is first
# imported, hence here, before anything imports it; a user's own setting stands.
os.environ.setdefault("ARROW_DEFAULT_MEMORY_POOL", "system")
# Nothing downloads from a model or dataset hub at run time: a checkpoint that names a
# sub-model by hub id (SmolVLA's VLM, X-VLA's tokenizer) resolves it from the local cache
# (make setup installs the zoo's) instead of asking the hub first, which offline cost minutes
# of retries per load. Read by huggingface_hub when first imported, hence here; a local Ray's
# actors inherit it; a user's own setting stands (HF_HUB_OFFLINE=0 allows downloads).
# pipeline.api.evaluate sets the same flags (pipeline.api.offline.OFFLINE_ENV) for its call,
# also in a process that imported huggingface_hub first.
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("HF_DATASETS_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

from pipeline.cli_list import add_list
from pipeline.cli_reliance import add_reliance
from pipeline.cli_results import add_compare, add_results, add_sidecar
from pipeline.cli_run import add_run, add_slurm
from pipeline.cli_study import add_study
from pipeline.cli_ui import add_ui
from pipeline.errors import RunError, is_disk_full
from pipeline.planning.config import ConfigError


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="idr-eval", description=__doc__)
    p.add_argument("-v", "--verbose", action="store_true")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (
        add_run,
        add_slurm,
        add_study,
        add_results,
        add_sidecar,
        add_compare,
        add_ui,
        add_list,
        add_reliance,
    ):
        add(sub)
    return p


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    # Overrides may follow --out; argparse leaves those after an option as unknown args.
    args, extra = parser.parse_known_args(argv)
    if extra:
        if args.command not in ("run", "slurm", "study") or any("=" not in e for e in extra):
            parser.error(f"unrecognized arguments: {' '.join(extra)}")
        args.overrides = [*args.overrides, *extra]
    from pipeline.execution.run_log import RUN_LOG

    RUN_LOG.install(verbose=args.verbose)
    try:
        return args.func(args)
    except ConfigError as e:
        print(f"idr-eval: error: {e}", file=sys.stderr)
        return 2
    except RunError as e:
        print(f"idr-eval: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:
        if not is_disk_full(e):
            raise
        print(
            f"idr-eval: error: no space left on the device ({e}); free space, then run the same "
            "command again to resume",
            file=sys.stderr,
        )
        return 1


if __name__ == "__main__":
    sys.exit(main())
