"""
The Noble-pinned job.

The package tests that need no ROS (pure core) run in a second venv with the library versions
Ubuntu 24.04 ships (scripts/noble/requirements.txt: numpy 1.26.4, SciPy 1.11.4, OpenCV 4.6, numba
0.58, ...), which is what `rosdep install` gives a stock Jazzy machine. `make test` creates the
venv first (scripts/noble_venv.sh, cached); where its wheels cannot be installed this test skips
with the reason the script recorded. Tests marked ``slow`` (multi-sample estimator-accuracy
runs of code the fast tests already exercise) are left out here: the main run has them, and
they made this job half the suite's time. In a full run the job starts in the background
right after collection (tests/noble_job.py, the root conftest.py).
"""

from pathlib import Path
import re
import subprocess
import sys

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
import noble_job  # noqa: E402, I100 (after the path insert)


def noble_python() -> Path:
    reason = noble_job.unavailable_reason()
    if reason is not None:
        pytest.skip(f'Noble-pinned venv unavailable: {reason}')
    return noble_job.VENV / 'bin' / 'python'


def test_pinned_versions_are_noble_s():
    python = noble_python()
    out = subprocess.run(
        [str(python), '-c', 'import numpy, scipy, cv2, numba, scipy.linalg.lapack as l; '
         'print(numpy.__version__, scipy.__version__, cv2.__version__, numba.__version__, '
         'hasattr(l, "dtrcon"))'],
        env=noble_job.clean_env(), capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    # SciPy 1.11 lacks dtrcon: the job really exercises ip_modeler's fallback
    assert out.stdout.split() == ['1.26.4', '1.11.4', '4.6.0', '0.58.1', 'False']


@pytest.mark.timeout(noble_job.TIMEOUT_S + 60)    # the job has its own limit
def test_pure_core_tests_pass_with_noble_versions():
    noble_python()
    code, out = noble_job.run()
    summary = out.strip().splitlines()[-1] if out.strip() else ''
    passed = int(m.group(1)) if (m := re.search(r'(\d+) passed', summary)) else 0
    assert code == 0, f'Noble-pinned core tests failed ({summary}):\n{out[-6000:]}'
    # the job must not silently shrink to nothing (e.g. every module skipped)
    assert passed >= 150, f'only {passed} core tests ran with Noble versions: {summary}'
    print(f'Noble-pinned core tests: {summary}')
