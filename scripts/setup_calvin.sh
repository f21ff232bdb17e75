#!/usr/bin/env bash
# The CALVIN env server's interpreter: a venv with Python 3.11 (PyBullet's wheels stop at
# cp311; lerobot needs 3.12, so CALVIN runs in an env server: env.python) and the pinned
# wheels of requirements-calvin.lock. Run by `make setup-calvin`, never by the main setup.
# Idempotent: when nothing changed, a second run takes a second.
# calvin_env itself (MIT, GitHub only) is a checkout you point at with CALVIN_ENV:
#   git clone --recurse-submodules https://github.com/mees/calvin && export CALVIN_ENV=$PWD/calvin/calvin_env
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${IDR_CALVIN_VENV:-.venv-calvin}
log() { printf '[setup-calvin] %s\n' "$*"; }
die() { printf '[setup-calvin] error: %s\n' "$*" >&2; exit 1; }

. scripts/find_python.sh

pinned_venv "$VENV" 3.11 requirements-calvin.lock "PyBullet, hydra, numpy..." scripts/setup_calvin.sh
"$VENV/bin/python" -c 'import pybullet, msgpack, numpy, hydra' 2>/dev/null \
    || die "$VENV cannot import pybullet/msgpack/numpy/hydra: remove it and run again"
log "ready: $VENV (Python $("$VENV/bin/python" -c 'import platform; print(platform.python_version())'))"
if [ -z "${CALVIN_ENV:-}" ]; then
    log "next: point CALVIN_ENV at a calvin_env checkout (docs/suites/calvin.md), then"
else
    log "CALVIN_ENV=$CALVIN_ENV"
fi
log "run: idr-eval run conf/calvin_smoke.yaml --out runs/calvin_smoke"
