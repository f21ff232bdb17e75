#!/usr/bin/env bash
# .venv-openpi: openpi's own websocket server and client packages (openpi-client pins numpy < 2,
# so they cannot share .venv), for the remote backbone's tests against the real server.
# Run by scripts/setup.sh; idempotent (a second run takes a second); ~15 s the first time.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${IDR_OPENPI_VENV:-.venv-openpi}
STAMP="$VENV/.idr-setup-stamp"
log() { printf '[setup-openpi] %s\n' "$*"; }
die() { printf '[setup-openpi] error: %s\n' "$*" >&2; exit 1; }
. scripts/find_python.sh

want=$(cat requirements-openpi.lock scripts/setup_openpi.sh | sha256sum | cut -d' ' -f1)
if [ -x "$VENV/bin/python" ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ]; then
    log "$VENV is up to date"
    exit 0
fi
if [ ! -x "$VENV/bin/python" ]; then
    py=$(find_python 3.12) || die "Python 3.12 not found; set PYTHON=/path/to/python3.12"
    "$py" -m venv "$VENV"
fi
log "installing openpi-server and openpi-client (numpy < 2) into $VENV"
"$VENV/bin/python" -m pip install -q --disable-pip-version-check -r requirements-openpi.lock
"$VENV/bin/python" -c 'import openpi_server, openpi_client' || die "$VENV cannot import openpi_server"
echo "$want" > "$STAMP"
log "ready: $VENV"
