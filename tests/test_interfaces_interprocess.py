"""Every stereo_manip_msgs message and service crosses a process boundary over DDS intact."""

from pathlib import Path
import subprocess
import sys

import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from stereo_manip_msgs import msg as msgs, srv as srvs

from stereo_manip_tools.testing import fill_message, make_node, shutdown_node, spin_until, \
    wait_for_subscribers

MESSAGES = ['ContactElement', 'ContactPair', 'ContactState', 'JointEstimate',
            'ImplicitPolynomial', 'TrackStatus']
SERVICES = ['CorrectTrajectory', 'EstimateJoint', 'FitImplicitPolynomial']


@pytest.fixture(scope='module')
def peer():
    proc = subprocess.Popen([sys.executable, str(Path(__file__).with_name(
        'interface_echo_peer.py'))], stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    node = make_node()
    try:
        assert spin_until(node, lambda: proc.poll() is not None or 'interface_echo_peer' in [
            n for n, _ in node.get_node_names_and_namespaces()], 30), 'peer did not start'
        assert proc.poll() is None, proc.stdout.read().decode()
        yield node
    finally:
        shutdown_node(node)
        proc.terminate()
        proc.wait(10)


@pytest.mark.process
@pytest.mark.parametrize('name', MESSAGES)
def test_message_round_trip(peer, name):
    node = peer
    cls = getattr(msgs, name)
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    received = []
    sub = node.create_subscription(cls, f'/roundtrip/out/{name}', received.append, qos)
    pub = node.create_publisher(cls, f'/roundtrip/in/{name}', qos)
    sent = [fill_message(cls, seed) for seed in range(3)]
    assert sent[0] != sent[1], 'filler must produce distinct messages'
    assert spin_until(node, lambda: sub.get_publisher_count() > 0, 15)
    assert wait_for_subscribers(node, [pub], 15)
    for m in sent:
        pub.publish(m)
    assert spin_until(node, lambda: len(received) >= 3, 15), f'got {len(received)} of 3'
    for got, want in zip(received, sent):
        for field in cls.get_fields_and_field_types():
            assert getattr(got, field) == getattr(want, field), f'{name}.{field} differs'
    node.destroy_subscription(sub)
    node.destroy_publisher(pub)


@pytest.mark.process
@pytest.mark.parametrize('name', SERVICES)
def test_service_round_trip(peer, name):
    node = peer
    cls = getattr(srvs, name)
    client = node.create_client(cls, f'/roundtrip/{name}')
    assert spin_until(node, client.service_is_ready, 15)
    future = client.call_async(fill_message(cls.Request, 7))
    assert spin_until(node, future.done, 15)
    response = future.result()
    assert response.success, 'peer saw a request different from what was sent'
    want = fill_message(cls.Response, 42)
    for field in cls.Response.get_fields_and_field_types():
        if field != 'success':
            assert getattr(response, field) == getattr(want, field), f'{name}.{field} differs'
    node.destroy_client(client)
