#!/usr/bin/env bash
# The full test suite (pure core, in-process rclpy, executables as processes). Assumes
# bootstrap has run (make test does both). Extra arguments go to pytest.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
set +u
# shellcheck disable=SC1091
. scripts/env.sh
set -u
exec python -m pytest -q "$@"
