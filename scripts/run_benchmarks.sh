#!/usr/bin/env bash
# Run every benchmark bench/<name>.py (or those named: run_benchmarks.sh camera_render_rate);
# each writes bench/results/<name>.json.
set -euo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
cd "$ROOT"
set +u
# shellcheck disable=SC1091
. scripts/env.sh
set -u
names=("$@")
if [ ${#names[@]} -eq 0 ]; then
  for f in bench/*.py; do names+=("$(basename "$f" .py)"); done
fi
status=0
for n in "${names[@]}"; do
  echo "=== bench/$n.py"
  python "bench/$n.py" || { echo "bench/$n.py failed"; status=1; }
done
exit $status
