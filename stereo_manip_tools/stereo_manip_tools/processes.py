"""
Package executables as their own processes, the way ``ros2 run`` starts them.

Used by the test harness and by the demo pipeline runner. The executable is found through the
ament index (``<prefix>/lib/<package>/<executable>``), output goes to a temporary log file, and
:meth:`ExecutableProcess.stop` sends SIGINT first, as Ctrl-C would.
"""

from __future__ import annotations

import os
from pathlib import Path
import signal
import subprocess
import tempfile
import time
from typing import Any, Callable, Optional, Sequence, Union
import uuid

import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

__all__ = ['make_node', 'shutdown_node', 'spin_until', 'wait_for_settled_graph',
           'executable_path', 'ExecutableProcess', 'interrupt_then_kill', 'process_cpu_seconds',
           'process_age_seconds']


def make_node(name: Optional[str] = None) -> Node:
    """Make a node in a fresh rclpy Context (destroy with ``shutdown_node``)."""
    context = Context()
    rclpy.init(context=context)
    return rclpy.create_node(name or f'test_{uuid.uuid4().hex[:8]}', context=context)


def shutdown_node(node: Node) -> None:
    """Destroy a node made by :func:`make_node` and shut its context down."""
    context = node.context
    node.destroy_node()
    rclpy.try_shutdown(context=context)


def spin_until(nodes: Union[Node, Sequence[Node]], predicate: Callable[[], bool],
               timeout: float = 10.0) -> bool:
    """
    Spin nodes until ``predicate()`` is true or ``timeout`` [s] expires.

    Spin one node, or several nodes of one context together (e.g. a node under test and the
    test's own node), until ``predicate()`` is true or ``timeout`` [s] expires; returns it.
    """
    group = [nodes] if isinstance(nodes, Node) else list(nodes)
    executor = SingleThreadedExecutor(context=group[0].context)
    for node in group:
        executor.add_node(node)
    try:
        deadline = time.monotonic() + timeout
        while not predicate():
            if time.monotonic() > deadline:
                return bool(predicate())
            executor.spin_once(timeout_sec=0.02)
        return True
    finally:
        for node in group:
            executor.remove_node(node)
        executor.shutdown()


def wait_for_settled_graph(observer: Node, node_names: Sequence[str], settle: float = 1.0,
                           timeout: float = 20.0) -> bool:
    """
    Spin ``observer`` until the topics of ``node_names`` stop changing; return whether they did.

    A node is in the graph before its constructor has created every publisher and subscription
    (and before the other processes have matched them): a message published at once, such as
    the first trigger of a triggered camera, can cross a link that is not there yet and be lost
    (measured: 2 of 3 triggered runs of ``bench/localizer_live.py`` lost their first frame, the
    demo its first peg frame). This waits until the publishers and subscriptions of every named
    node (root namespace) have been the same for ``settle`` [s], within ``timeout`` [s].
    """
    def endpoints() -> tuple:
        out = []
        for name in node_names:
            try:
                pubs = observer.get_publisher_names_and_types_by_node(name, '/')
                subs = observer.get_subscriber_names_and_types_by_node(name, '/')
            except Exception:  # noqa: BLE001 - NodeNameNonExistentError: not up yet
                return ()
            out.append((name, tuple(sorted(t for t, _ in pubs)),
                        tuple(sorted(t for t, _ in subs))))
        return tuple(out)

    state = {'last': None, 'since': time.monotonic()}

    def settled() -> bool:
        now, current = time.monotonic(), endpoints()
        if current != state['last'] or not current:
            state['last'], state['since'] = current, now
            return False
        return now - state['since'] >= settle
    return spin_until(observer, settled, timeout)


def executable_path(package: str, executable: str) -> Path:
    """
    ``<prefix of package>/lib/<package>/<executable>`` from the ament index (as ros2 run).

    :raises FileNotFoundError: package not in the index or executable not installed.
    """
    from ament_index_python.packages import get_package_prefix

    path = Path(get_package_prefix(package)) / 'lib' / package / executable
    if not os.access(path, os.X_OK):
        raise FileNotFoundError(f'no executable {executable!r} installed for {package!r} '
                                f'(looked for {path})')
    return path


def interrupt_then_kill(process: subprocess.Popen, timeout: float = 10.0) -> Optional[int]:
    """
    Stop ``process`` as Ctrl-C would: SIGINT, then SIGKILL if still running after ``timeout`` [s].

    :returns: its exit code (negative: the signal that ended it); nothing is sent to a process
        that has already exited.
    """
    if process.poll() is None:
        process.send_signal(signal.SIGINT)
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)
    return process.returncode


class ExecutableProcess:
    """A package executable running as its own process; output captured to a temp file."""

    def __init__(self, package: str, executable: str, args: Sequence[str] = (),
                 ros_args: Sequence[str] = (), env: Optional[dict] = None) -> None:
        self.command = [str(executable_path(package, executable)), *args]
        if ros_args:
            self.command += ['--ros-args', *ros_args]
        self._log = tempfile.NamedTemporaryFile(prefix=f'{executable}_', suffix='.log',
                                                delete=False)
        full_env = dict(os.environ)
        full_env.setdefault('PYTHONUNBUFFERED', '1')
        full_env.update(env or {})
        self.process = subprocess.Popen(self.command, stdout=self._log,
                                        stderr=subprocess.STDOUT, env=full_env)

    def output(self) -> str:
        """Everything the process printed so far (stdout and stderr)."""
        self._log.flush()
        return Path(self._log.name).read_text(errors='replace')

    def running(self) -> bool:
        """Tell whether the process has not exited yet."""
        return self.process.poll() is None

    def wait_for_node(self, observer: Node, node_name: str, timeout: float = 30.0) -> bool:
        """Spin ``observer`` until ``node_name`` is in the graph (or the process died)."""
        def seen() -> bool:
            if not self.running():
                return True
            return node_name in [n for n, _ in observer.get_node_names_and_namespaces()]
        spin_until(observer, seen, timeout)
        return self.running() and node_name in [
            n for n, _ in observer.get_node_names_and_namespaces()]

    def wait_for_output(self, text: str, timeout: float = 30.0) -> bool:
        """Wait until ``text`` appears in the output or the process exits."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if text in self.output():
                return True
            if not self.running():
                return text in self.output()
            time.sleep(0.05)
        return False

    def stop(self, timeout: float = 10.0) -> int:
        """SIGINT (as Ctrl-C), then SIGKILL after ``timeout`` [s]; returns the exit code."""
        return interrupt_then_kill(self.process, timeout)

    def __enter__(self) -> 'ExecutableProcess':
        return self

    def __exit__(self, *exc: Any) -> None:
        self.stop()
        self._log.close()
        try:
            os.unlink(self._log.name)
        except OSError:
            pass


def process_cpu_seconds(pid: int) -> float:
    """Return utime + stime [s] of a process from /proc (NaN once it has gone)."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf('SC_CLK_TCK')
    except (OSError, IndexError, ValueError):
        return float('nan')


def process_age_seconds(pid: int | str = 'self') -> float:
    """Return the seconds since a process started, from /proc (NaN once it has gone)."""
    try:
        fields = Path(f'/proc/{pid}/stat').read_text().rsplit(')', 1)[1].split()
        start = int(fields[19]) / os.sysconf('SC_CLK_TCK')     # field 22: starttime
        return time.clock_gettime(time.CLOCK_BOOTTIME) - start
    except (OSError, IndexError, ValueError):
        return float('nan')
