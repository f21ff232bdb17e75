#!/usr/bin/env bash
# One-command setup, shared by the README path, CI and the Docker images:
# a .venv with Python 3.12 and the pinned dependencies (requirements.lock), the system
# libraries headless MuJoCo rendering needs, and LIBERO's assets + config for offline use.
# Idempotent: when nothing changed, a second run takes seconds.
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${IDR_VENV:-.venv}
UV_VERSION=0.13.8
STAMP="$VENV/.idr-setup-stamp"
log() { printf '[setup] %s\n' "$*"; }
die() { printf '[setup] error: %s\n' "$*" >&2; exit 1; }

. scripts/find_python.sh

# --- system packages: headless rendering (OSMesa; EGL comes with GPU drivers), and Debian's
# chromium for the MLflow UI test (driven by Playwright; no browser is downloaded) -----------
have_lib() { ldconfig -p 2>/dev/null | grep -q "$1"; }
can_apt() { [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; }
apt_updated=0
apt_install() {
    [ "$apt_updated" = 1 ] || { apt-get update -qq >/dev/null && apt_updated=1; } || return 1
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "$@" >/dev/null
}
if ! have_lib 'libOSMesa.so'; then
    can_apt || die "libOSMesa is missing: install Debian/Ubuntu package libosmesa6 (sudo apt-get install libosmesa6)"
    log "installing libosmesa6 (headless OpenGL for MuJoCo without a GPU)"
    apt_install libosmesa6 || die "could not install libosmesa6 with apt-get"
fi
# IDR_SKIP_BROWSER=1: no browser (the Docker images, which run episodes, not the UI test). A
# browser that cannot be installed is not fatal: the one test that needs it skips, saying why.
if [ "${IDR_SKIP_BROWSER:-0}" != 1 ] && ! command -v chromium >/dev/null; then
    if can_apt; then
        log "installing chromium (the MLflow UI test's browser, ~20 s)"
        apt_install chromium || log "could not install chromium: the MLflow UI browser test will skip"
    else
        log "chromium is not installed (sudo apt-get install chromium): the MLflow UI browser test will skip"
    fi
fi

# IDR_SKIP_SLURM=1: no Slurm daemons (the Docker images). The Slurm tests start a real
# slurmctld and slurmd from Debian's slurm-wlm and munge (root only); without them they skip,
# saying why.
if [ "${IDR_SKIP_SLURM:-0}" != 1 ] && ! command -v slurmctld >/dev/null; then
    if can_apt; then
        log "installing slurm-wlm and munge (the Slurm tests' daemons, ~30 s)"
        apt_install slurm-wlm munge iproute2 || log "could not install slurm-wlm: the Slurm tests will skip"
    else
        log "slurm-wlm is not installed (sudo apt-get install slurm-wlm munge): the Slurm tests will skip"
    fi
fi

# --- the virtual environment ---------------------------------------------------------------
want=$(cat requirements.lock pyproject.toml lerobot_policy_idr/pyproject.toml scripts/setup.sh scripts/find_python.sh scripts/top_level_cache.py | sha256sum | cut -d' ' -f1)
if [ -x "$VENV/bin/python" ] && [ -f "$STAMP" ] && [ "$(cat "$STAMP")" = "$want" ]; then
    log "$VENV is up to date"
else
    if [ ! -x "$VENV/bin/python" ]; then
        py=$(find_python 3.12) || die "Python 3.12 not found (looked for python3.12 on PATH and in pyenv); install it or set PYTHON=/path/to/python3.12"
        log "creating $VENV with $py"
        "$py" -m venv "$VENV"
    fi
    "$VENV/bin/python" -c 'import sys; assert sys.version_info[:2] == (3, 12)' \
        || die "$VENV is not Python 3.12: remove it and run again"
    if ! "$VENV/bin/uv" --version 2>/dev/null | grep -q "$UV_VERSION"; then
        "$VENV/bin/python" -m pip install -q "uv==$UV_VERSION"
    fi
    log "installing pinned dependencies (first time: several minutes, torch is large)"
    "$VENV/bin/uv" pip install -q --python "$VENV/bin/python" -r requirements.lock
    "$VENV/bin/uv" pip install -q --python "$VENV/bin/python" --no-deps -e .
    # the method as a lerobot policy plugin (lerobot-eval / lerobot-rollout in .venv find it
    # by its name); the harness imports the refiner from it
    "$VENV/bin/uv" pip install -q --python "$VENV/bin/python" --no-deps -e lerobot_policy_idr
    # transformers and diffusers map packages to distributions when imported (every process
    # that loads a policy): with each wheel's top_level.txt written once, 0.17 s instead of 1.2
    "$VENV/bin/python" scripts/top_level_cache.py >/dev/null
    # bytecode written once here: every process (actors, CLI calls, tests) then imports torch,
    # lerobot, pandas... without compiling them, also where PYTHONDONTWRITEBYTECODE is set (as
    # on the CI machines, where nothing would otherwise ever be cached: measured, `idr-eval
    # report` imports 7.4 -> ~2 s). The packages' own test folders are never imported: skipped.
    # A few dependency files are not Python 3.
    log "compiling the dependencies' bytecode (once)"
    site=$("$VENV/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
    "$VENV/bin/python" -m compileall -q -j 0 -x '/tests/' "$site" >/dev/null 2>&1 || true
    echo "$want" > "$STAMP"
fi

# --- openpi's server packages in their own venv (numpy < 2): the remote backbone's tests ----
bash scripts/setup_openpi.sh

# --- LIBERO offline: link packaged assets, write the config (never prompts) ----------------
"$VENV/bin/python" -m workers.envs.suites.libero.assets >/dev/null

# --- the zoo's tokenizers / VLM configs into the local Hugging Face cache, by their hub ids --
"$VENV/bin/python" -m training.zoo_hub install >/dev/null
log "ready: $VENV (Python $("$VENV/bin/python" -c 'import platform; print(platform.python_version())'))"
