#!/usr/bin/env bash
# One-time, idempotent set-up of a fresh Debian machine: the apt packages for headless EGL
# rendering (Mesa llvmpipe) and a .venv with Python 3.11, bpy 5.0.1 and the core's wheels.
set -euo pipefail
cd "$(dirname "$0")/.."

APT_PACKAGES="libegl1 libegl-mesa0 libgl1-mesa-dri libgl1 libglx-mesa0 libxkbcommon0 libsm6 libxi6 libxrender1 libxxf86vm1 libxfixes3"
missing=""
for p in $APT_PACKAGES; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing="$missing $p"
done
if [ -n "$missing" ]; then
  echo "setup: installing apt packages:$missing" >&2
  SUDO=""
  [ "$(id -u)" -ne 0 ] && command -v sudo >/dev/null && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq $missing >/dev/null
fi

PY=""
for cand in python3.11 python3; do
  if command -v "$cand" >/dev/null && "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))'; then
    PY="$cand"; break
  fi
done
if [ -z "$PY" ]; then
  echo "setup: Python 3.11 is required (bpy 5.0.1 is built for it); none found on PATH" >&2
  exit 1
fi
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[blender,dev,bench]"
.venv/bin/python -c "import bpy, embreex, fast_simplification, numpy; print('setup: ok, bpy', bpy.app.version_string)"
