"""The record and replay executables, started from the install tree as their own processes."""

import time

import numpy as np
import pytest
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message, serialize_message
from std_msgs.msg import String
from stereo_manip_msgs.msg import ContactState, JointEstimate

from stereo_manip_tools.bag_io import bag_summary, BagError, BagWriter, get_message_class, \
    read_bag
from stereo_manip_tools.testing import fill_message, spin_until, start_executable, \
    wait_for_subscribers

QOS = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)


def test_custom_types_round_trip_through_a_bag(tmp_path):
    sent = [fill_message(ContactState, k) for k in range(3)]
    with BagWriter(tmp_path / 'b', 'mcap') as writer:
        writer.add_topic('/contact_state', 'stereo_manip_msgs/msg/ContactState')
        for k, m in enumerate(sent):
            writer.write('/contact_state', 1000 + k, serialize_message(m))
    back = list(read_bag(tmp_path / 'b'))
    assert [m.timestamp for m in back] == [1000, 1001, 1002]
    assert [deserialize_message(m.data, ContactState) for m in back] == sent
    topics, start, end = bag_summary(tmp_path / 'b')
    assert topics == {'/contact_state': ('stereo_manip_msgs/msg/ContactState', 3)}
    assert (start, end) == (1000, 1002)


def test_sqlite3_storage_also_works(tmp_path):
    with BagWriter(tmp_path / 'b', 'sqlite3') as writer:
        writer.add_topic('/s', 'std_msgs/msg/String')
        writer.write('/s', 5, serialize_message(String(data='x')))
    assert deserialize_message(next(read_bag(tmp_path / 'b')).data, String).data == 'x'


def test_bag_errors_are_clear(tmp_path):
    with pytest.raises(BagError, match='does not exist'):
        list(read_bag(tmp_path / 'missing'))
    with pytest.raises(BagError, match='not a rosbag2 bag'):
        list(read_bag(tmp_path))
    with pytest.raises(BagError, match='unknown message type'):
        get_message_class('no_such_pkg/msg/Thing')
    with BagWriter(tmp_path / 'b') as writer:
        with pytest.raises(BagError, match='unknown to the bag type store'):
            writer.add_topic('/x', 'no_such_pkg/msg/Thing')


@pytest.mark.process
def test_executables_appear_in_the_graph(ros_node, tmp_path):
    with start_executable('stereo_manip_tools', 'record', '-o', str(tmp_path / 'b'), '/idle',
                          '--wait', '60', observer=ros_node, wait_for_node='bag_recorder'):
        pass
    with BagWriter(tmp_path / 'c') as writer:
        writer.add_topic('/s', 'std_msgs/msg/String')
        for k in range(30):
            writer.write('/s', k * 200_000_000, serialize_message(String(data=str(k))))
    with start_executable('stereo_manip_tools', 'replay', str(tmp_path / 'c'),
                          observer=ros_node, wait_for_node='bag_replayer'):
        pass


@pytest.mark.process
@pytest.mark.parametrize('args, expected', [
    (['replay', '{tmp}/missing'], 'does not exist'),
    (['replay', '{tmp}'], 'not a rosbag2 bag'),
    (['replay', '{bag}', '--topics', '/nope'], 'not in bag'),
    (['replay', '{odd}'], 'unknown message type'),
    (['record', '-o', '{bag}', '/x'], 'already exists'),
])
def test_bad_input_exits_nonzero_without_traceback(tmp_path, args, expected):
    with BagWriter(tmp_path / 'bag') as writer:
        writer.add_topic('/s', 'std_msgs/msg/String')
        writer.write('/s', 1, serialize_message(String(data='x')))
    # A bag whose topic type has no installed interface package (rosbags knows the type).
    with BagWriter(tmp_path / 'odd') as writer:
        writer.add_topic('/odd', 'statistics_msgs/msg/MetricsMessage')
        writer.write('/odd', 1, b'\x00\x01\x00\x00\x00\x00\x00\x00')
    exe, *rest = [a.format(tmp=tmp_path, bag=tmp_path / 'bag', odd=tmp_path / 'odd')
                  for a in args]
    with start_executable('stereo_manip_tools', exe, *rest) as proc:
        proc.process.wait(30)
        out = proc.output()
    assert proc.process.returncode != 0
    assert expected in out and 'Traceback' not in out


@pytest.mark.process
def test_record_then_replay_gives_identical_messages_with_original_spacing(
        ros_node, tmp_path):
    node = ros_node
    pub_je = node.create_publisher(JointEstimate, '/test_bag/joint', QOS)
    pub_s = node.create_publisher(String, '/test_bag/text', QOS)
    bag = tmp_path / 'recorded'
    gaps = [0.03, 0.08, 0.05, 0.12, 0.02, 0.06]
    sent = []
    published_at = []
    with start_executable('stereo_manip_tools', 'record', '-o', str(bag), '/test_bag/joint',
                          '/test_bag/text', observer=node,
                          wait_for_node='bag_recorder') as rec:
        # wait until the recorder subscribed to both topics
        assert wait_for_subscribers(node, [pub_je, pub_s]), rec.output()
        for k in range(24):
            m = fill_message(JointEstimate, k)
            published_at.append(time.monotonic())
            pub_je.publish(m)
            pub_s.publish(String(data=f'text {k}'))
            sent.append(m)
            time.sleep(gaps[k % len(gaps)])
        spin_until(node, lambda: False, 0.5)
    topics, _, _ = bag_summary(bag)
    assert topics['/test_bag/joint'][1] == 24 and topics['/test_bag/text'][1] == 24
    stamps = [m.timestamp for m in read_bag(bag, ['/test_bag/joint'])]

    received = []
    sub = node.create_subscription(JointEstimate, '/test_bag/joint',
                                   lambda m: received.append((time.monotonic(), m)), QOS)
    with start_executable('stereo_manip_tools', 'replay', str(bag), '--topics',
                          '/test_bag/joint', '--wait-subscribers', '1', observer=node,
                          wait_for_node='bag_replayer'):
        assert spin_until(node, lambda: len(received) >= 24, 30), len(received)
    node.destroy_subscription(sub)
    assert [m for _, m in received] == sent
    arrival_gaps = [b[0] - a[0] for a, b in zip(received, received[1:])]
    bag_gaps = [(b - a) / 1e9 for a, b in zip(stamps, stamps[1:])]
    # Paced like the recording: the arrival gaps follow the recorded ones (a replay that
    # ignored the stamps would send all 24 at once) and the whole replay lasts as long. The
    # receiving side adds scheduling jitter to single gaps on a loaded machine, so single gaps
    # are judged by their median error and their correlation with the recorded gaps.
    errors = np.abs(np.subtract(arrival_gaps, bag_gaps))
    assert np.median(errors) < 0.005, f'median spacing error {np.median(errors) * 1e3:.1f} ms'
    assert np.corrcoef(arrival_gaps, bag_gaps)[0, 1] > 0.9, (arrival_gaps, bag_gaps)
    total = (received[-1][0] - received[0][0]) - (stamps[-1] - stamps[0]) / 1e9
    assert abs(total) < 0.03, f'replay took {total * 1e3:+.1f} ms longer than the recording'
    # the recorded spacing itself follows the publisher's
    pub_gaps = [b - a for a, b in zip(published_at, published_at[1:])]
    assert np.median(np.abs(np.subtract(bag_gaps, pub_gaps))) < 0.005
    assert np.corrcoef(bag_gaps, pub_gaps)[0, 1] > 0.9
