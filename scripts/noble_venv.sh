#!/usr/bin/env bash
# Noble-pinned venv for the test job tests/test_noble_pinned.py: the libraries at the versions
# Ubuntu 24.04 ships (scripts/noble/requirements.txt), to catch code that only works with the
# newer wheels of requirements.txt (e.g. scipy.linalg.lapack.dtrcon, new in SciPy 1.12).
#
# The venv is cached outside the work tree, keyed by the pin file's hash, so a fresh clone on the
# same machine (CI) reuses it: $STEREO_MANIP_NOBLE_VENV, else
# ${XDG_CACHE_HOME:-~/.cache}/stereo_manip/venv-noble-<hash>; `.venv-noble` links to it.
# When the wheels cannot be installed (no network, no wheel for this platform) it writes the
# reason to .venv-noble.skip and exits 0: the test job then skips with that reason.
set -uo pipefail
ROOT=$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)
PINS=$ROOT/scripts/noble/requirements.txt
PY=${PYTHON:-python3.11}
SKIP=$ROOT/.venv-noble.skip
say() { printf '[noble-venv] %s\n' "$*"; }

hash=$(sha256sum "$PINS" | cut -c1-12)
VENV=${STEREO_MANIP_NOBLE_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/stereo_manip/venv-noble-$hash}
if [ -f "$VENV/.complete" ]; then
  ln -sfn "$VENV" "$ROOT/.venv-noble"
  rm -f "$SKIP"
  exit 0
fi
skip() { say "skipped: $*"; printf '%s\n' "$*" > "$SKIP"; rm -f "$ROOT/.venv-noble"; exit 0; }
command -v "$PY" >/dev/null || skip "$PY not found"
say "creating $VENV (first run: downloads the Noble-pinned wheels, a few minutes)"
rm -rf "$VENV"
mkdir -p "$(dirname "$VENV")"
"$PY" -m venv "$VENV" || skip "could not create a venv with $PY"
log=$(mktemp)
if ! "$VENV/bin/pip" install -q --disable-pip-version-check --only-binary=:all: -r "$PINS" \
    >"$log" 2>&1; then
  reason=$(grep -E 'ERROR' "$log" | head -2 | tr '\n' ' ')
  rm -rf "$VENV" "$log"
  skip "the Noble-pinned wheels could not be installed: ${reason:-pip failed}"
fi
rm -f "$log"
touch "$VENV/.complete"
ln -sfn "$VENV" "$ROOT/.venv-noble"
rm -f "$SKIP"
say 'ready'
