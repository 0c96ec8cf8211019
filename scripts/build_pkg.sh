#!/usr/bin/env bash
# build_pkg.sh PKG [PKG...]: colcon build of only the named packages (after editing
# setup.cfg/setup.py or adding data files; Python edits need no rebuild: --symlink-install).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
# shellcheck disable=SC1091
. "$ROOT/.venv/bin/activate"
CALLER_AMENT_PREFIX_PATH=${AMENT_PREFIX_PATH:-}
export AMENT_PREFIX_PATH=$ROOT/.venv CMAKE_PREFIX_PATH=$ROOT/.venv
cd "$ROOT"
# shellcheck source=compat_packages.sh
. "$ROOT/scripts/compat_packages.sh"
mapfile -t COMPAT_DIRS < <(compat_package_dirs "$ROOT" "$ROOT/.venv:$CALLER_AMENT_PREFIX_PATH")
colcon --log-base "$ROOT/log" build --base-paths msgs stereo_manip_models stereo_manip_tools stereo_depth \
  object_localizer contact_correction joint_estimator ip_modeler stereo_manip_bringup \
  "${COMPAT_DIRS[@]}" \
  --build-base build --install-base install --symlink-install --packages-select "$@" \
  --event-handlers console_direct- --cmake-args -DBUILD_TESTING=OFF
