#!/usr/bin/env bash
# `make test`, what CI runs (.ci/run): the Noble-pinned venv, its job started in the background
# right away (it needs neither ROS nor the colcon build: the pure-core tests run from the source
# folders, tests/noble_job.py), the bootstrap meanwhile, then the full suite, whose
# tests/test_noble_pinned.py collects the job's result. Extra arguments go to pytest.
# STEREO_MANIP_NOBLE_BACKGROUND=0: no background job (the suite runs it in its own turn).
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
PY=${PYTHON:-python3.11}
scripts/noble_venv.sh
if [ "${STEREO_MANIP_NOBLE_BACKGROUND:-1}" != 0 ]; then
  job=$(mktemp -d "${TMPDIR:-/tmp}/stereo_manip_noble.XXXXXX")
  trap '"$PY" tests/noble_job.py cancel "$job"; rm -rf "$job"' EXIT
  "$PY" tests/noble_job.py start "$job"
  export STEREO_MANIP_NOBLE_JOB_DIR=$job
fi
scripts/bootstrap.sh
scripts/run_tests.sh "$@"
