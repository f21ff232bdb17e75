#!/usr/bin/env bash
# The SIMPLER env server: a Python 3.11 venv (.venv-simpler; sapien 2.2.2 has wheels up to cp311,
# lerobot needs 3.12, so SIMPLER runs in an env server: env.python) with the pinned wheels of
# requirements-simpler.lock, and, on a machine without a GPU Vulkan driver, .vulkan-cpu: Mesa's
# lavapipe from Debian bookworm-backports (25.0.7; bookworm's 22.3 is refused by SAPIEN), unpacked
# into the folder (no system package changes), and our layer (scripts/vulkan_cpu/) compiled.
# Run by `make setup-simpler`, never by the main setup. Idempotent.
# ManiSkill2_real2sim (Apache-2.0, GitHub only) is a checkout you point at with MS2_REAL2SIM:
#   git clone https://github.com/simpler-env/ManiSkill2_real2sim && export MS2_REAL2SIM=$PWD/ManiSkill2_real2sim
set -euo pipefail
cd "$(dirname "$0")/.."

VENV=${IDR_SIMPLER_VENV:-.venv-simpler}
VK=${IDR_VULKAN_CPU:-.vulkan-cpu}
log() { printf '[setup-simpler] %s\n' "$*"; }
die() { printf '[setup-simpler] error: %s\n' "$*" >&2; exit 1; }

. scripts/find_python.sh

pinned_venv "$VENV" 3.11 requirements-simpler.lock "SAPIEN 2.2.2, gymnasium 0.29, numpy 1.26..." scripts/setup_simpler.sh
"$VENV/bin/python" -c 'import importlib.util as u, sys; sys.exit(any(u.find_spec(m) is None for m in ("sapien", "gymnasium", "transforms3d", "msgpack")))' \
    || die "$VENV lacks sapien/gymnasium/transforms3d/msgpack: remove it and run again"

# -- Vulkan on the CPU -----------------------------------------------------------------------------
layer_src=scripts/vulkan_cpu/semaphore_fd_layer.c
vk_want=$(cat "$layer_src" scripts/setup_simpler.sh | sha256sum | cut -d' ' -f1)
if ls /usr/share/vulkan/icd.d/nvidia_icd*.json /etc/vulkan/icd.d/nvidia_icd*.json >/dev/null 2>&1 \
    && [ -z "${IDR_FORCE_LAVAPIPE:-}" ]; then
    log "a GPU Vulkan driver is installed: SAPIEN renders on it (env.params.renderer=auto)"
elif [ -f "$VK/lvp.json" ] && [ "$(cat "$VK/.stamp" 2>/dev/null)" = "$vk_want" ]; then
    log "$VK is up to date"
else
    log "building $VK: lavapipe from bookworm-backports (Mesa 25.0.7) and the layer"
    tmp=$(mktemp -d); trap 'rm -rf "$tmp"' EXIT
    mkdir -p "$tmp/lists/partial" "$tmp/debs" "$tmp/root"
    echo "deb http://deb.debian.org/debian bookworm-backports main" > "$tmp/backports.list"
    A=(-o Dir::Etc::sourcelist="$tmp/backports.list" -o Dir::Etc::sourceparts=/dev/null
       -o Dir::State::Lists="$tmp/lists" -o Debug::NoLocking=1)
    apt-get "${A[@]}" update -qq || die "cannot reach bookworm-backports (apt-get update)"
    (cd "$tmp/debs" \
        && apt-get "${A[@]}" download -qq mesa-vulkan-drivers/bookworm-backports \
            libdrm2/bookworm-backports libdrm-amdgpu1/bookworm-backports \
        && apt-get download -qq libvulkan1 libvulkan-dev) 2>&1 | grep -v "unsandboxed" || true
    ls "$tmp"/debs/mesa-vulkan-drivers_*.deb "$tmp"/debs/libvulkan-dev_*.deb >/dev/null \
        || die "could not download the Mesa Vulkan packages"
    for deb in "$tmp"/debs/*.deb; do dpkg-deb -x "$deb" "$tmp/root"; done
    rm -rf "$VK" && mkdir -p "$VK/lib" "$VK/layer"
    lib="$tmp/root/usr/lib/x86_64-linux-gnu"
    cp -a "$lib"/libvulkan_lvp.so "$lib"/libdrm.so.2* "$lib"/libdrm_amdgpu.so.1* "$lib"/libvulkan.so.1* "$VK/lib/"
    abs=$(cd "$VK" && pwd)
    sed "s#\"library_path\": \"[^\"]*\"#\"library_path\": \"$abs/lib/libvulkan_lvp.so\"#" \
        "$tmp/root/usr/share/vulkan/icd.d/lvp_icd.json" > "$VK/lvp.json"
    cc -O2 -Wall -Wextra -shared -fPIC -I"$tmp/root/usr/include" -o "$VK/layer/libVkLayer_IDR_semaphore_fd.so" \
        "$layer_src" -lpthread || die "cannot compile $layer_src (gcc is needed)"
    cat > "$VK/layer/VkLayer_IDR_semaphore_fd.json" <<'JSON'
{
    "file_format_version": "1.1.2",
    "layer": {
        "name": "VK_LAYER_IDR_semaphore_fd",
        "type": "GLOBAL",
        "library_path": "./libVkLayer_IDR_semaphore_fd.so",
        "api_version": "1.3.239",
        "implementation_version": "1",
        "description": "lists VK_KHR_external_semaphore_fd for SAPIEN 2 on lavapipe (idr-eval)"
    }
}
JSON
    dpkg-deb -f "$tmp"/debs/mesa-vulkan-drivers_*.deb Version | sed 's/^/Mesa /' > "$VK/VERSION"
    echo "$vk_want" > "$VK/.stamp"
fi
if [ -f "$VK/lvp.json" ]; then
    "$VENV/bin/python" -c "
import sys; sys.path.insert(0, '.')
from workers.envs.suites.simpler import vulkan_cpu
print(vulkan_cpu.configure('$VK'))
import sapien.core as sapien
sapien.SapienRenderer(offscreen_only=True)" >/dev/null 2>&1 \
        || die "SAPIEN does not start on $VK's lavapipe: remove $VK and run again"
    log "SAPIEN renders on lavapipe ($(cat "$VK/VERSION")): $VK"
fi
log "ready: $VENV (Python $("$VENV/bin/python" -c 'import platform; print(platform.python_version())'))"
[ -n "${MS2_REAL2SIM:-}${SIMPLER_ENV:-}" ] || log "next: point MS2_REAL2SIM at a ManiSkill2_real2sim checkout (docs/suites/simpler.md), then"
log "run: idr-eval run conf/simpler_smoke.yaml --out runs/simpler_smoke"
