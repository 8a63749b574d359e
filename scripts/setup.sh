#!/usr/bin/env bash
# One-command set-up of a fresh machine (Debian 12 / Python >= 3.11):
# system libraries open3d links against, a virtualenv in .venv, the project and its tested versions.
set -euo pipefail
cd "$(dirname "$0")/.."

PY=${PYTHON:-python3}
VENV=${VENV:-.venv}
SYSTEM_PACKAGES=(libgl1 libgomp1 libusb-1.0-0 libegl1 libx11-6 chromium poppler-utils openssl iproute2)
# GigE Vision sensors (drivers/laser/gige): Aravis's library and typelib, its command-line tools
# (arv-tool-0.8) and its fake GigE Vision device (arv-fake-gv-camera-0.8, in aravis-tools) that the
# tests and the benchmark run against; PyGObject (pyproject.toml) builds against the -dev packages.
SYSTEM_PACKAGES+=(gir1.2-aravis-0.8 aravis-tools-cli aravis-tools
    libgirepository1.0-dev libcairo2-dev pkg-config gcc python3-dev)
# CloudCompare's command line opens the exported clouds in a test (tests/analysis/test_cloud_export.py),
# headless under Qt's offscreen platform
SYSTEM_PACKAGES+=(cloudcompare)
# node-opcua, the independent OPC UA client tests/opcua drives the server with (npm ci, below; npm
# comes with NodeSource's nodejs, or Debian's npm package)
SYSTEM_PACKAGES+=(nodejs)

missing=()
for pkg in "${SYSTEM_PACKAGES[@]}"; do
    dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
if ((${#missing[@]})); then
    if [[ $(id -u) -ne 0 ]]; then
        echo "setup: missing system packages: ${missing[*]}" >&2
        echo "setup: run as root, or first: sudo apt-get update && sudo apt-get install -y ${missing[*]}" >&2
        exit 1
    fi
    echo "setup: installing system packages: ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -qq
    apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

if ! "$PY" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
    echo "setup: $PY is $("$PY" --version 2>&1); cellctl needs Python >= 3.11" >&2
    exit 1
fi
if [[ ! -x "$VENV/bin/python" ]]; then
    if ! "$PY" -m venv "$VENV" 2>/dev/null; then
        if [[ $(id -u) -eq 0 ]]; then
            apt-get update -qq && apt-get install -y -qq python3-venv >/dev/null
            "$PY" -m venv "$VENV"
        else
            echo "setup: '$PY -m venv' failed; install python3-venv" >&2
            exit 1
        fi
    fi
fi
"$VENV/bin/python" -m pip install -q --upgrade pip
"$VENV/bin/python" -m pip install -q -c constraints.txt -e ".[dev]"
"$VENV/bin/python" -c 'import open3d, pinocchio, zenoh, ruckig, toppra, gi; gi.require_version("Aravis", "0.8")' \
    || { echo "setup: the installed packages do not import (see above)" >&2; exit 1; }
# Debian's nodejs ships npm apart (NodeSource's carries it): install it when it is missing
if ! command -v npm >/dev/null && [[ $(id -u) -eq 0 ]]; then
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends npm >/dev/null \
        || { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends npm >/dev/null; }
fi
command -v npm >/dev/null || { echo "setup: npm missing (apt-get install npm, or NodeSource's nodejs)" >&2; exit 1; }
npm ci --prefix tests/opcua/node --no-audit --no-fund --loglevel=error >/dev/null \
    || { echo "setup: npm ci in tests/opcua/node failed (node-opcua for the OPC UA tests)" >&2; exit 1; }
echo "setup: ok ($("$VENV/bin/cellctl" --version))"
