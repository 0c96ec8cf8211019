#!/usr/bin/env bash
# The main job: the demo pipeline on the built-in synthetic scenes (a live graph of separate
# processes), scored against ground truth. Report in demo_output/report.md. Extra arguments go
# to the demo (e.g. --frames 0.5 for a quicker run, --stages peg_in_hole).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
exec scripts/ros2run stereo_manip_bringup demo --out "$ROOT/demo_output" "$@"
