"""interrupt_then_kill: SIGINT first (as Ctrl-C), SIGKILL only for a process that ignores it."""

import signal
import subprocess
import sys
import time

import pytest
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


@pytest.mark.ros
def test_the_graph_wait_returns_after_a_late_publisher_appears():
    """A node's topics created after it joined the graph are waited for (first-trigger race)."""
    import threading

    from std_msgs.msg import Empty
    from stereo_manip_tools.processes import make_node, shutdown_node, spin_until, \
        wait_for_settled_graph
    observer, late = make_node(), make_node('late_graph_node')
    try:
        assert spin_until(observer, lambda: 'late_graph_node' in [
            n for n, _ in observer.get_node_names_and_namespaces()], 20.0)
        # the publisher comes after the node was seen, within one settle period: a wait that
        # returned once the node is in the graph (``wait_for_node``) would miss it
        timer = threading.Timer(0.4, lambda: late.create_publisher(Empty, 'late_topic', 1))
        timer.start()
        assert wait_for_settled_graph(observer, ['late_graph_node'], settle=1.5, timeout=20.0)
        timer.join()
        topics = [t for t, _ in observer.get_publisher_names_and_types_by_node(
            'late_graph_node', '/')]
        assert '/late_topic' in topics
        # a node that is not there: not settled
        assert not wait_for_settled_graph(observer, ['no_such_node'], settle=0.2, timeout=1.0)
    finally:
        shutdown_node(late)
        shutdown_node(observer)
