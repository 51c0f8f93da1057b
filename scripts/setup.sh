#!/usr/bin/env bash
# One-time, idempotent set-up of a fresh Debian machine: the apt packages for headless EGL
# rendering (Mesa llvmpipe) and a virtual environment with the bpy of one Blender version and the
# core's wheels.
#
#   BLENDER=4.2|4.5|5.0|5.3 bash scripts/setup.sh [VENV]
#
# Blender 4.2-5.0 ship Python 3.11, 5.1 and later Python 3.13: each bpy wheel only installs into
# its own Python (pyenv's 3.13 is found through PYENV_VERSION where python3.13 is not on PATH).
set -euo pipefail
cd "$(dirname "$0")/.."

BLENDER="${BLENDER:-5.0}"
case "$BLENDER" in
  4.2) BPY="4.2.23"; PYTHON="3.11" ;;
  4.5) BPY="4.5.15"; PYTHON="3.11" ;;
  5.0) BPY="5.0.1";  PYTHON="3.11" ;;
  5.3) BPY="5.3.0";  PYTHON="3.13" ;;
  *) echo "setup: BLENDER must be 4.2, 4.5, 5.0 or 5.3, got '$BLENDER'" >&2; exit 2 ;;
esac
VENV="${1:-.venv}"

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

is_wanted() { "$@" -c "import sys; sys.exit(sys.version_info[:2] != tuple(map(int, '$PYTHON'.split('.'))))" 2>/dev/null; }
PY=()
for cand in "python$PYTHON" python3; do
  if command -v "$cand" >/dev/null && is_wanted "$cand"; then PY=("$cand"); break; fi
done
if [ ${#PY[@]} -eq 0 ] && command -v pyenv >/dev/null; then
  version="$(pyenv versions --bare | grep -E "^${PYTHON//./\\.}(\.[0-9]+)?$" | sort -V | tail -n 1 || true)"
  if [ -n "$version" ] && is_wanted env PYENV_VERSION="$version" "python$PYTHON"; then
    PY=(env PYENV_VERSION="$version" "python$PYTHON")
  fi
fi
if [ ${#PY[@]} -eq 0 ]; then
  echo "setup: Python $PYTHON is required (bpy $BPY is built for it); none found on PATH or in pyenv" >&2
  exit 1
fi
[ -x "$VENV/bin/python" ] || "${PY[@]}" -m venv "$VENV"

# The bpy wheels are 300-430 MB: a dropped connection or a full disk must not end the set-up on a
# first try nor leave a half-written environment behind. pip resumes a broken download itself
# (--resume-retries, pip 25.1+); a failed install is tried again from the start after a pause.
pip_install() {
  local attempt
  for attempt in 1 2 3; do
    if "$VENV/bin/python" -m pip install -q --retries 10 --timeout 60 "$@"; then return 0; fi
    echo "setup: pip install $* failed (try $attempt of 3); free disk: $(df -h . | awk 'NR==2 {print $4}')" >&2
    [ "$attempt" -lt 3 ] && sleep $((attempt * 20))
  done
  return 1
}
pip_install --upgrade pip
pip_install --resume-retries 20 -e ".[dev]" "bpy==$BPY"
"$VENV/bin/python" -c "import bpy, embreex, fast_simplification, numpy; print('setup: ok, bpy', bpy.app.version_string, 'numpy', numpy.__version__)"
