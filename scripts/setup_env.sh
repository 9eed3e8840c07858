#!/usr/bin/env bash
# Create .venv with the pinned dependencies and make Mitsuba's LLVM variant runnable.
# Used by `make`; safe to re-run. Works on a fresh Debian machine as root with python3.11 and pip.
set -euo pipefail
PY="${PY:-python3.11}"
VENV="${VENV:-.venv}"

if [ ! -x "$VENV/bin/python" ]; then
    if ! "$PY" -m venv "$VENV" 2>/dev/null; then
        rm -rf "$VENV"
        if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
            echo "setup: installing python3-venv with apt-get" >&2
            apt-get update -q >/dev/null && apt-get install -y -q python3-venv python3.11-venv >/dev/null || true
        fi
        "$PY" -m venv "$VENV"
    fi
fi
"$VENV/bin/pip" install -q torch==2.13.0
"$VENV/bin/pip" install -q -r requirements.lock
"$VENV/bin/pip" install -q --no-deps --no-build-isolation -e .

# Mitsuba's llvm_ad_rgb aborts the process with libLLVM 15 ("Cannot select ... fminimum");
# libLLVM 19 fixes it. Probe in a subprocess, install it where we can.
probe='import mitsuba as mi; mi.set_variant("llvm_ad_rgb"); mi.render(mi.load_dict(mi.cornell_box()), spp=1)'
if ! "$VENV/bin/python" -c "$probe" >/dev/null 2>&1; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
        echo "setup: Mitsuba's llvm variant cannot run; installing libllvm19 with apt-get" >&2
        apt-get update -q >/dev/null && apt-get install -y -q libllvm19 >/dev/null || true
    fi
    if ! "$VENV/bin/python" -c "$probe" >/dev/null 2>&1; then
        echo "setup: warning: Mitsuba's llvm_ad_rgb still cannot run; rendering falls back to scalar_rgb (slow)" >&2
    fi
fi
