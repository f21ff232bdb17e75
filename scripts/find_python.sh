# Sourced by the setup scripts: find_python X.Y prints an interpreter of that version (the
# PYTHON variable, pythonX.Y on PATH, pyenv's versions, /usr/local/bin, /usr/bin), or fails.
find_python() {
    local want=$1 c
    for c in "${PYTHON:-}" "python$want" "${PYENV_ROOT:-$HOME/.pyenv}"/versions/"$want"*/bin/"python$want" \
        "/usr/local/bin/python$want" "/usr/bin/python$want"; do
        [ -n "$c" ] || continue
        if "$c" -c "import sys; assert '%d.%d' % sys.version_info[:2] == '$want'" >/dev/null 2>&1; then
            command -v "$c" || echo "$c"
            return 0
        fi
    done
    return 1
}

# pinned_venv VENV X.Y LOCK WHAT [FILE...]: VENV (Python X.Y) with the wheels of LOCK installed;
# a no-op when LOCK, the FILEs (the calling script) and this file are unchanged since the last
# run (a stamp in VENV). WHAT names the wheels in the log. Needs the caller's log and die.
pinned_venv() {
    local venv=$1 version=$2 lock=$3 what=$4 py want
    shift 4
    want=$(cat "$lock" "$@" scripts/find_python.sh | sha256sum | cut -d' ' -f1)
    if [ -x "$venv/bin/python" ] && [ "$(cat "$venv/.idr-setup-stamp" 2>/dev/null)" = "$want" ]; then
        log "$venv is up to date"
        return 0
    fi
    if [ ! -x "$venv/bin/python" ]; then
        py=$(PYTHON=${PYTHON311:-} find_python "$version") || die "Python $version not found (looked for python$version on PATH and in pyenv); install it (pyenv install $version) or set PYTHON311=/path/to/python$version"
        log "creating $venv with $py"
        "$py" -m venv "$venv"
    fi
    "$venv/bin/python" -c "import sys; assert '%d.%d' % sys.version_info[:2] == '$version'" \
        || die "$venv is not Python $version: remove it and run again"
    log "installing the pinned wheels ($what; about a minute)"
    "$venv/bin/python" -m pip install -q --disable-pip-version-check -r "$lock"
    local site
    site=$("$venv/bin/python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')
    "$venv/bin/python" -m compileall -q -j 0 -x '/tests/' "$site" >/dev/null 2>&1 || true
    echo "$want" > "$venv/.idr-setup-stamp"
}
