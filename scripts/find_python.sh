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
