"""
The Noble-pinned job's hand-over (tests/noble_job.py), with stand-in jobs.

``make test`` starts the job before the bootstrap and the suite collects its result from a
folder (scripts/make_test.sh): a finished job's exit code and output must reach the test, an
unfinished one must be waited for, and one that never ends must be killed, not waited on forever.
"""

import os
from pathlib import Path
import signal
import subprocess
import sys
import time

sys.path.insert(0, str(Path(__file__).resolve().parent))
import noble_job  # noqa: E402, I100 (after the path insert)


def test_finished_job_hands_its_exit_code_and_output_to_the_suite(tmp_path, monkeypatch):
    script = 'import time; time.sleep(1.0); print("7 passed"); raise SystemExit(3)'
    monkeypatch.setattr(noble_job, 'command', lambda: [sys.executable, '-c', script])
    (tmp_path / 'pid').write_text(str(os.getpid()))
    monkeypatch.setenv(noble_job.EARLY_DIR_ENV, str(tmp_path))
    job = noble_job.attach()
    assert isinstance(job, noble_job.EarlyJob)
    assert not (tmp_path / 'rc').exists()
    assert noble_job._run_early(tmp_path) == 3
    assert job.result(timeout=5.0) == (3, '7 passed\n')
    job.cancel()                        # finished: nothing to stop (our own pid is in 'pid')


def test_no_folder_or_no_pid_means_no_early_job(tmp_path, monkeypatch):
    monkeypatch.delenv(noble_job.EARLY_DIR_ENV, raising=False)
    assert noble_job.attach() is None
    monkeypatch.setenv(noble_job.EARLY_DIR_ENV, str(tmp_path))   # venv unavailable: no pid
    assert noble_job.attach() is None


def test_job_that_does_not_finish_is_killed_with_its_process_group(tmp_path):
    child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)'],
                             start_new_session=True)
    try:
        (tmp_path / 'pid').write_text(str(child.pid))
        t0 = time.monotonic()
        code, out = noble_job.EarlyJob(tmp_path).result(timeout=1.0)
        assert code == -signal.SIGKILL and 'killed after 1 s' in out
        assert child.wait(10.0) == -signal.SIGKILL
        assert time.monotonic() - t0 < 10.0
    finally:
        if child.poll() is None:
            child.kill()


def test_job_stops_when_make_test_is_gone(tmp_path, monkeypatch):
    monkeypatch.setattr(noble_job, 'command', lambda: [
        sys.executable, '-c', 'import time; time.sleep(60)'])
    owner = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(1.0)'])
    t0 = time.monotonic()
    code = noble_job._run_early(tmp_path, owner.pid)
    owner.wait()
    assert code == -signal.SIGKILL and time.monotonic() - t0 < 20.0
    assert 'make test ended' in (tmp_path / 'output.txt').read_text()
    assert (tmp_path / 'rc').read_text() == str(-signal.SIGKILL)
