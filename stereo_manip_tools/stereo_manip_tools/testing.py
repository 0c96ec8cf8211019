"""
Test harness shared by every package (a pytest plugin loaded by the root ``conftest.py``).

- fixture ``ros_node``: an in-process rclpy node in its own ``Context``, destroyed after the test;
- :func:`spin_until`, :func:`wait_for_message`, :func:`collect_messages`: spin until a condition
  holds or a timeout expires (never forever); :func:`wait_for_subscribers` before the first
  message of a test that counts every message;
- :func:`start_executable`: start ``install/<pkg>/lib/<pkg>/<exe>`` as its own process, exactly
  what ``ros2 run`` does, wait until its node is in the graph, and stop it with SIGINT at exit.

The session's ``ROS_DOMAIN_ID`` is random and discovery is localhost-only (root conftest.py),
so tests never see another session's graph.
"""

from __future__ import annotations

from typing import Any, Iterator, List, Optional, Sequence

import pytest
from rclpy.node import Node
from stereo_manip_tools.processes import (
    executable_path, ExecutableProcess, make_node, shutdown_node, spin_until)

__all__ = [
    'ros_node',
    'make_node',
    'shutdown_node',
    'spin_until',
    'wait_for_message',
    'wait_for_subscribers',
    'call_service',
    'collect_messages',
    'executable_path',
    'ExecutableProcess',
    'start_executable',
    'fill_message',
]


@pytest.fixture
def ros_node() -> Iterator[Node]:
    """Provide an in-process rclpy node with its own Context, for the duration of one test."""
    node = make_node()
    try:
        yield node
    finally:
        shutdown_node(node)


def collect_messages(node: Node, msg_type: Any, topic: str, count: int, timeout: float = 10.0,
                     qos: Any = 10) -> List[Any]:
    """Subscribe to ``topic`` and return the first ``count`` messages (fewer on timeout)."""
    received: List[Any] = []
    sub = node.create_subscription(msg_type, topic, received.append, qos)
    try:
        spin_until(node, lambda: len(received) >= count, timeout)
    finally:
        node.destroy_subscription(sub)
    return received[:count]


def call_service(nodes: Any, srv_type: Any, name: str, request: Any,
                 timeout: float = 30.0) -> Any:
    """
    Call service ``name`` and return the response.

    Call service ``name`` from the first of ``nodes`` (spinning all of them, so an in-process
    server can answer) and return the response; fails the test if the service does not come up
    or answer within ``timeout`` [s].
    """
    group = [nodes] if isinstance(nodes, Node) else list(nodes)
    client = group[0].create_client(srv_type, name)
    try:
        assert spin_until(group, client.service_is_ready, timeout), f'{name} not available'
        future = client.call_async(request)
        assert spin_until(group, future.done, timeout), f'{name} did not answer in {timeout} s'
        return future.result()
    finally:
        group[0].destroy_client(client)


def wait_for_message(node: Node, msg_type: Any, topic: str, timeout: float = 10.0,
                     qos: Any = 10) -> Any:
    """Wait for the first message on ``topic`` within ``timeout`` [s]; None if none came."""
    msgs = collect_messages(node, msg_type, topic, 1, timeout, qos)
    return msgs[0] if msgs else None


def wait_for_subscribers(node: Node, publishers: Sequence[Any], timeout: float = 20.0,
                         settle: float = 1.0) -> bool:
    """
    Wait until every publisher has a matched subscription, then ``settle`` seconds more.

    A publisher sees the remote reader before the remote side has matched the writer; a
    message sent in between is lost (volatile durability), which is harmless for streams but
    not for a test that counts every message, hence the settling time.

    :returns: False when some publisher found no subscription within ``timeout`` [s].
    """
    if not spin_until(node, lambda: all(p.get_subscription_count() > 0 for p in publishers),
                      timeout):
        return False
    spin_until(node, lambda: False, settle)
    return True


def start_executable(package: str, executable: str, *args: str, ros_args: Sequence[str] = (),
                     observer: Optional[Node] = None, wait_for_node: Optional[str] = None,
                     timeout: float = 30.0, env: Optional[dict] = None) -> ExecutableProcess:
    """
    Start an installed executable as its own process (``ros2 run`` semantics).

    With ``wait_for_node`` (and an ``observer`` node to look at the graph) it waits until that
    node appears and raises ``RuntimeError`` with the process output if it does not.
    Use as a context manager so the process is always stopped.
    """
    proc = ExecutableProcess(package, executable, args, ros_args, env)
    if wait_for_node is not None:
        own = observer is None
        obs = make_node() if own else observer
        try:
            ok = proc.wait_for_node(obs, wait_for_node, timeout)
        finally:
            if own:
                shutdown_node(obs)
        if not ok:
            proc.stop()
            raise RuntimeError(f'{package}/{executable}: node {wait_for_node!r} did not appear '
                               f'within {timeout} s; output:\n{proc.output()}')
    return proc


_INT_RANGES = {'int8': 127, 'uint8': 255, 'int16': 32767, 'uint16': 65535, 'int32': 2**31 - 1,
               'uint32': 2**32 - 1, 'int64': 2**63 - 1, 'uint64': 2**64 - 1, 'octet': 255,
               'char': 127, 'byte': 255}


def fill_message(msg_class: Any, seed: int = 0, depth: int = 0) -> Any:
    """
    Make a message of ``msg_class`` with every field set to a non-default pseudo-random value.

    Sequences get 1-3 elements, nested messages are filled recursively, so a round trip that
    drops or mangles any field shows up in ``==``.
    """
    import importlib
    import random

    rng = random.Random(seed * 7919 + depth)
    msg = msg_class()

    def value(type_name: str) -> Any:
        base = type_name.split('<', 1)[-1].rstrip('>') if type_name.startswith('sequence<') \
            else type_name
        base = base.split('[')[0]
        if base.startswith(('string', 'wstring')):
            return f'{base}-{rng.randrange(10**6)}'
        if base == 'boolean':
            return True
        if base in ('float', 'double', 'float32', 'float64'):
            return rng.uniform(-100.0, 100.0) if base in ('double', 'float64') else \
                float(int(rng.uniform(-100, 100) * 64) / 64)
        if base in _INT_RANGES:
            top = _INT_RANGES[base]
            v = rng.randint(1, min(top, 10**6))
            if base == 'byte' or base == 'octet':
                return bytes([v % 256])
            return v
        pkg, name = base.split('/')
        module = importlib.import_module(f'{pkg}.msg')
        return fill_message(getattr(module, name), rng.randrange(10**6), depth + 1)

    for field, type_name in msg_class.get_fields_and_field_types().items():
        if type_name.startswith('sequence<'):
            n = rng.randint(1, 3)
            items = [value(type_name) for _ in range(n)]
            setattr(msg, field, items)
        elif type_name.endswith(']'):
            size = int(type_name.split('[')[1].rstrip(']'))
            setattr(msg, field, [value(type_name) for _ in range(size)])
        else:
            setattr(msg, field, value(type_name))
    return msg
