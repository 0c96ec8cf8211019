"""interrupt_then_kill: SIGINT first (as Ctrl-C), SIGKILL only for a process that ignores it."""

import signal
import subprocess
import sys
import time

from stereo_manip_tools.processes import interrupt_then_kill, process_age_seconds


def _python(code):
    proc = subprocess.Popen([sys.executable, '-c', code], stdout=subprocess.PIPE)
    assert proc.stdout.readline() == b'ready\n'     # its signal handling is set up
    return proc


def test_a_process_that_handles_sigint_ends_with_its_own_exit_code():
    proc = _python('import signal, sys, time\n'
                   'signal.signal(signal.SIGINT, lambda *_: sys.exit(3))\n'
                   'print("ready", flush=True)\ntime.sleep(30)')
    assert interrupt_then_kill(proc, timeout=10.0) == 3


def test_a_process_ignoring_sigint_is_killed_after_the_timeout():
    proc = _python('import signal, time\nsignal.signal(signal.SIGINT, signal.SIG_IGN)\n'
                   'print("ready", flush=True)\ntime.sleep(30)')
    t0 = time.monotonic()
    assert interrupt_then_kill(proc, timeout=0.5) == -signal.SIGKILL
    assert 0.5 <= time.monotonic() - t0 < 10.0


def test_an_exited_process_gets_no_signal():
    proc = subprocess.Popen([sys.executable, '-c', 'raise SystemExit(4)'])
    proc.wait(30)
    assert interrupt_then_kill(proc) == 4


def test_process_age_is_the_time_since_the_process_started():
    t0 = time.monotonic()
    child = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(30)'])
    try:
        time.sleep(1.0)
        age = process_age_seconds(child.pid)
        # /proc start times are in clock ticks (10 ms)
        assert 1.0 - 0.05 <= age <= time.monotonic() - t0 + 0.05, age
    finally:
        child.kill()
        child.wait()
    assert process_age_seconds('self') > 0.0
    assert process_age_seconds(2 ** 30) != process_age_seconds(2 ** 30)    # gone: NaN
