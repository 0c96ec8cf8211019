"""
The Noble-pinned job's command, environment and background run (tests/test_noble_pinned.py).

The job is single-threaded and needs no ROS, so a full `make test` starts it in the background
as soon as the suite is collected (the root conftest.py) and runs this venv's pure-core tests
meanwhile: two single-threaded runs on two cores. The rclpy and process tiers, whose timing
matters more, run after ``test_pure_core_tests_pass_with_noble_versions`` has collected the
job's result.
"""

import os
from pathlib import Path
import subprocess
import tempfile
from typing import Dict, List, Optional, Tuple

ROOT = Path(__file__).resolve().parents[1]
VENV = ROOT / '.venv-noble'
SKIP_REASON = ROOT / '.venv-noble.skip'
PACKAGES = ['stereo_manip_tools', 'stereo_depth', 'object_localizer', 'contact_correction',
            'joint_estimator', 'ip_modeler', 'stereo_manip_bringup']
#: the job's time limit [s]
TIMEOUT_S = 1500.0


def unavailable_reason() -> Optional[str]:
    """Return why the Noble-pinned venv cannot be used, or None when it can."""
    if (VENV / 'bin' / 'python').exists():
        return None
    return SKIP_REASON.read_text().strip() if SKIP_REASON.exists() else \
        'not created (run scripts/noble_venv.sh; make test does)'


def clean_env() -> Dict[str, str]:
    """Return an environment with no trace of the main venv or the ROS install tree."""
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(('AMENT_', 'COLCON_', 'CMAKE_', 'ROS_', 'RMW_', 'PYTHON'))
           and k not in ('VIRTUAL_ENV', 'LD_LIBRARY_PATH')}
    env['PYTHONPATH'] = os.pathsep.join([str(ROOT / p) for p in PACKAGES]
                                        + [str(ROOT / 'scripts' / 'noble')])
    # numba's on-disk cache is keyed by numba version: keep Noble's apart from the main venv's
    env['NUMBA_CACHE_DIR'] = str(VENV.resolve() / 'numba_cache')
    env['PATH'] = f"{VENV / 'bin'}{os.pathsep}{env.get('PATH', '')}"
    return env


def command() -> List[str]:
    """Return the job's pytest command: the package tests but the rclpy, process, slow tiers."""
    return [str(VENV / 'bin' / 'python'), '-m', 'pytest', '--confcutdir=scripts', '-p',
            'noble_plugin', '-q', '-rs', '-m', 'not ros and not process and not slow',
            '-p', 'no:cacheprovider', *[f'{p}/test' for p in PACKAGES]]


class BackgroundJob:
    """The job running as a child process, its output in a temporary file."""

    def __init__(self) -> None:
        self.log = tempfile.TemporaryFile(mode='w+')
        self.process = subprocess.Popen(command(), cwd=ROOT, env=clean_env(), text=True,
                                        stdout=self.log, stderr=subprocess.STDOUT)

    def result(self, timeout: float = TIMEOUT_S) -> Tuple[int, str]:
        """Wait for the job; return its exit code and output (killed after ``timeout`` s)."""
        try:
            code = self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            code = self.process.wait()
        self.log.seek(0)
        return code, self.log.read()

    def cancel(self) -> None:
        """Stop the job if it still runs (the session ended without collecting it)."""
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait()


#: the job started by the root conftest.py for this session, if any
background: Optional[BackgroundJob] = None


def run() -> Tuple[int, str]:
    """Return the job's exit code and output: the background run's, else a run now."""
    if background is not None:
        return background.result()
    result = subprocess.run(command(), cwd=ROOT, env=clean_env(), capture_output=True,
                            text=True, timeout=TIMEOUT_S)
    return result.returncode, result.stdout + result.stderr
