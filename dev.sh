#!/usr/bin/env bash
# room-pipeline developer entry point.
#   ./dev.sh setup     install Debian libraries + a pinned virtualenv in .venv (idempotent, fast when done)
#   ./dev.sh pipeline  setup, then `dvc repro` on the default (phantom) configuration
#   ./dev.sh test      setup, then the test suite (what CI runs)
set -euo pipefail
cd "$(dirname "$0")"

VENV=.venv
PY=${PYTHON:-python3.11}
command -v "$PY" >/dev/null 2>&1 || PY=python3
# Debian runtime libraries: open3d needs libusb; bpy (Blender) needs the X/GL client libraries even headless
# (libgl1/libegl1 also give VTK/pyvista off-screen EGL rendering); chromium checks the HTML report in a test.
DEB_PKGS="libusb-1.0-0 libgl1 libegl1 libxrender1 libxi6 libxkbcommon0 libsm6 libxxf86vm1 libxfixes3 libgomp1 chromium"
# torch must be the local CPU wheel: from PyPI it would pull GBs of CUDA packages
WHEELS=${ROOM_WHEELS:-/opt/wheels}

log() { printf '[dev.sh] %s\n' "$*" >&2; }

need_root() {
    if [ "$(id -u)" = 0 ]; then "$@"; elif command -v sudo >/dev/null; then sudo "$@"; else
        log "need root to run: $*"; exit 1; fi
}

setup_debian() {
    command -v dpkg-query >/dev/null || { log "not a Debian system: install the equivalents of: $DEB_PKGS"; return 0; }
    local missing=""
    for p in $DEB_PKGS; do
        dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
    done
    if ! "$PY" -c 'import ensurepip, venv' >/dev/null 2>&1; then missing="$missing python3-venv"; fi
    if [ -n "$missing" ]; then
        log "installing Debian packages:$missing"
        need_root env DEBIAN_FRONTEND=noninteractive apt-get update -qq
        need_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends $missing >/dev/null
    fi
}

setup_python() {
    "$PY" -c 'import sys; assert sys.version_info[:2] == (3, 11), sys.version' 2>/dev/null || {
        log "Python 3.11 is required (bpy 5.0 ships for 3.11 only); found: $("$PY" --version 2>&1)"; exit 1; }
    local stamp="$VENV/.room-setup"
    local want extras="dev"
    if compgen -G "$WHEELS/torch-2.13.0+cpu-*.whl" >/dev/null; then
        extras="dev,ml"
    else
        log "no local CPU torch wheel in $WHEELS: skipping the 'ml' extra (depth CNN / torch dataset tests will skip)"
    fi
    want=$( (cat constraints.txt pyproject.toml; echo "$extras") | sha256sum | cut -d' ' -f1)
    if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$VENV/bin/room" ]; then
        return 0   # already set up with exactly these pins
    fi
    [ -x "$VENV/bin/python" ] || "$PY" -m venv "$VENV"
    log "installing pinned Python packages into $VENV (constraints.txt)"
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade "pip>=23" setuptools wheel
    "$VENV/bin/python" -m pip install -q --disable-pip-version-check --find-links "$WHEELS" -c constraints.txt \
        -e ".[$extras]"
    if [[ "$extras" == *ml* ]]; then   # TotalSegmentator's network classes; --no-deps: timm would pull another torch
        "$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-deps -c constraints.txt \
            dynamic-network-architectures
    fi
    echo "$want" > "$stamp"
}

setup() { setup_debian; setup_python; }

case "${1:-}" in
    setup) setup ;;
    pipeline) setup; shift; PATH="$PWD/$VENV/bin:$PATH" dvc repro "$@" ;;
    test) setup; shift; PATH="$PWD/$VENV/bin:$PATH" "$VENV/bin/python" -m pytest "$@" ;;
    *) echo "usage: ./dev.sh {setup|pipeline|test} [args...]" >&2; exit 2 ;;
esac
