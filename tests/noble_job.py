"""
The Noble-pinned job's command, environment and background run (tests/test_noble_pinned.py).

The job is single-threaded and needs neither ROS nor the colcon build (the pure-core tests run
from the source folders), so `make test` (scripts/make_test.sh) starts it in the background
before the bootstrap: ``python tests/noble_job.py start DIR`` (output and exit code in DIR,
handed to the suite as ``$STEREO_MANIP_NOBLE_JOB_DIR``). A suite run without such a job starts
one as soon as it is collected (the root conftest.py). Either way this venv's pure-core tests run
meanwhile: two single-threaded runs on two cores. The rclpy and process tiers, whose timing
matters more, run after ``test_pure_core_tests_pass_with_noble_versions`` has collected the
job's result.
"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import tempfile
import time
from typing import Dict, List, Optional, Tuple, Union

ROOT = Path(__file__).resolve().parents[1]
VENV = ROOT / '.venv-noble'
SKIP_REASON = ROOT / '.venv-noble.skip'
PACKAGES = ['stereo_manip_tools', 'stereo_depth', 'object_localizer', 'contact_correction',
            'joint_estimator', 'ip_modeler', 'stereo_manip_bringup']
#: the job's time limit [s]
TIMEOUT_S = 1500.0
#: environment variable naming the folder of a job started before the suite (scripts/make_test.sh)
EARLY_DIR_ENV = 'STEREO_MANIP_NOBLE_JOB_DIR'


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


class EarlyJob:
    """
    The job ``python tests/noble_job.py start DIR`` started before the suite.

    DIR holds ``pid`` (the job's wrapper, leader of its own process group), ``output.txt``
    and, once it has finished, ``rc`` (its exit code).
    """

    def __init__(self, folder: Path) -> None:
        self.folder = folder

    def _done(self) -> bool:
        return (self.folder / 'rc').exists()

    def result(self, timeout: float = TIMEOUT_S) -> Tuple[int, str]:
        """Wait for the job; return its exit code and output (killed after ``timeout`` s)."""
        end = time.monotonic() + timeout
        while not self._done() and time.monotonic() < end:
            time.sleep(0.5)
        if not self._done():
            self.cancel()
            return -signal.SIGKILL, self._output() + f'\n[job killed after {timeout:.0f} s]'
        return int((self.folder / 'rc').read_text()), self._output()

    def _output(self) -> str:
        out = self.folder / 'output.txt'
        return out.read_text(errors='replace') if out.exists() else ''

    def cancel(self) -> None:
        """Stop the job if it still runs (the session ended without collecting it)."""
        if self._done():
            return
        try:
            os.killpg(int((self.folder / 'pid').read_text()), signal.SIGKILL)
        except (OSError, ValueError):
            pass


def attach() -> Optional[EarlyJob]:
    """Return the job started before this suite (``$STEREO_MANIP_NOBLE_JOB_DIR``), if any."""
    folder = os.environ.get(EARLY_DIR_ENV)
    if folder and (Path(folder) / 'pid').is_file():
        return EarlyJob(Path(folder))
    return None


def _start_early(folder: Path) -> None:
    """
    Start the job in the background, its output and exit code in ``folder``.

    Nothing starts when the venv is unavailable: the suite's test then skips with the reason.
    The job stops when the process that asked for it (scripts/make_test.sh) is gone.
    """
    if unavailable_reason() is not None:
        return
    wrapper = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), 'run',
                                str(folder), str(os.getppid())], cwd=ROOT,
                               start_new_session=True, stdin=subprocess.DEVNULL,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    (folder / 'pid').write_text(str(wrapper.pid))


def _alive(pid: int) -> bool:
    """Tell whether process ``pid`` runs (a zombie does not)."""
    try:
        stat = Path(f'/proc/{pid}/stat').read_text()
    except OSError:
        return False
    return stat.rsplit(')', 1)[-1].split()[0] != 'Z'


def _run_early(folder: Path, owner: Optional[int] = None) -> int:
    """
    Run the job now, its output in ``folder``/output.txt, then write ``folder``/rc.

    No time limit here: the suite's wait has it (:meth:`EarlyJob.result`), as for a job it
    starts itself, so a slow bootstrap does not eat into the job's time. The job is killed if
    process ``owner`` ends first (``make test`` interrupted before the suite collected it).
    """
    with open(folder / 'output.txt', 'w') as out:
        job = subprocess.Popen(command(), cwd=ROOT, env=clean_env(), stdout=out,
                               stderr=subprocess.STDOUT)
        while True:
            try:
                code = job.wait(2.0)
                break
            except subprocess.TimeoutExpired:
                if owner is not None and not _alive(owner):
                    job.kill()
                    out.write('\n[job killed: make test ended]\n')
                    code = job.wait()
                    break
    (folder / 'rc.tmp').write_text(str(code))
    (folder / 'rc.tmp').rename(folder / 'rc')
    return code


#: the job of this session (started before it, or by the root conftest.py), if any
background: Optional[Union[BackgroundJob, EarlyJob]] = None


def run() -> Tuple[int, str]:
    """Return the job's exit code and output: the background run's, else a run now."""
    job = background or attach()
    if job is not None:
        return job.result()
    result = subprocess.run(command(), cwd=ROOT, env=clean_env(), capture_output=True,
                            text=True, timeout=TIMEOUT_S)
    return result.returncode, result.stdout + result.stderr


if __name__ == '__main__':
    # python tests/noble_job.py start|cancel DIR (scripts/make_test.sh); run DIR OWNER_PID
    action, where = sys.argv[1], Path(sys.argv[2])
    if action == 'start':
        _start_early(where)
    elif action == 'run':
        sys.exit(_run_early(where, int(sys.argv[3])))
    elif action == 'cancel':
        EarlyJob(where).cancel()
    else:
        sys.exit(f'unknown action {action!r}')
