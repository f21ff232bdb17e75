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
STAMP="$VENV/.idr-setup-stamp"
log() { printf '[setup-calvin] %s\n' "$*"; }
die() { printf '[setup-calvin] error: %s\n' "$*" >&2; exit 1; }

. scripts/find_python.sh

want=$(cat requirements-calvin.lock scripts/setup_calvin.sh scripts/find_python.sh | sha256sum | cut -d' ' -f1)
if [ -x "$VENV/bin/python" ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ]; then
    log "$VENV is up to date"
else
    if [ ! -x "$VENV/bin/python" ]; then
        py=$(PYTHON=${PYTHON311:-} find_python 3.11) || die "Python 3.11 not found (looked for python3.11 on PATH and in pyenv); install it (pyenv install 3.11) or set PYTHON311=/path/to/python3.11"
        log "creating $VENV with $py"
        "$py" -m venv "$VENV"
    fi
    "$VENV/bin/python" -c 'import sys; assert sys.version_info[:2] == (3, 11)' \
        || die "$VENV is not Python 3.11: remove it and run again"
    log "installing the pinned wheels (PyBullet, hydra, numpy...; about a minute)"
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check -r requirements-calvin.lock
    site=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
    "$VENV/bin/python" -m compileall -q -j 0 "$site" >/dev/null 2>&1 || true
    echo "$want" > "$STAMP"
fi
"$VENV/bin/python" -c 'import pybullet, msgpack, numpy, hydra' 2>/dev/null \
    || die "$VENV cannot import pybullet/msgpack/numpy/hydra: remove it and run again"
log "ready: $VENV (Python $("$VENV/bin/python" -c 'import platform; print(platform.python_version())'))"
if [ -z "${CALVIN_ENV:-}" ]; then
    log "next: point CALVIN_ENV at a calvin_env checkout (see the README: CALVIN), then"
else
    log "CALVIN_ENV=$CALVIN_ENV"
fi
log "run: idr-eval run conf/calvin_smoke.yaml --out runs/calvin_smoke"
