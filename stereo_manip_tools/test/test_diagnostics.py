"""
Diagnostics helper.

Rates and stamp ages against a controlled clock, counter warnings, and the published
DiagnosticArray of an in-process node.
"""

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
import pytest

from stereo_manip_tools.conversions import ns_to_stamp
from stereo_manip_tools.diagnostics import DiagnosticStatusWrapper, NodeDiagnostics, OK, \
    TopicStatus, WARN
from stereo_manip_tools.testing import make_node, shutdown_node, spin_until


class FakeClock:
    def __init__(self) -> None:
        self.ns = 1_000_000_000

    def __call__(self) -> int:
        return self.ns


def values(stat: DiagnosticStatusWrapper) -> dict:
    return dict(stat.values)


def test_topic_status_rate_and_age():
    clock = FakeClock()
    topic = TopicStatus('points2', min_rate=4.0, max_age=0.2, window=3, clock=clock)
    # 10 messages in 2 s, each 0.1 s old except one at 0.5 s
    for k in range(10):
        clock.ns += 200_000_000
        now = 50_000_000_000 + k * 200_000_000
        age = 500_000_000 if k == 9 else 100_000_000
        topic.tick(ns_to_stamp(now - age), now)
    stat = DiagnosticStatusWrapper('x')
    topic.run(stat)
    v = values(stat)
    assert float(v['points2 rate [Hz]']) == pytest.approx(5.0)
    assert float(v['points2 stamp age median [s]']) == pytest.approx(0.1)
    assert float(v['points2 stamp age max [s]']) == pytest.approx(0.5)
    assert stat.level == WARN and 'stamp age p95' in stat.message    # p95 of ages > 0.2 s
    # next period: 2 messages in 1 s -> 2 Hz < 4 Hz
    for _ in range(2):
        clock.ns += 500_000_000
        topic.tick()
    stat = DiagnosticStatusWrapper('x')
    topic.run(stat)
    v = values(stat)
    assert float(v['points2 rate [Hz]']) == pytest.approx(2.0)
    assert float(v['points2 mean rate [Hz]']) == pytest.approx(12 / 3.0)
    assert 'points2 stamp age median [s]' not in v             # no stamps this period
    assert stat.level == WARN and '2.00 Hz < 4.00 Hz' in stat.message


def test_merge_summary_keeps_the_worst():
    stat = DiagnosticStatusWrapper('x')
    stat.summary(OK, 'fine')
    stat.merge_summary(WARN, 'a')
    stat.merge_summary(WARN, 'b')
    stat.merge_summary(OK, 'c')
    assert (stat.level, stat.message) == (WARN, 'a; b')
    assert stat.to_msg().level == DiagnosticStatus.WARN


@pytest.mark.ros
def test_node_diagnostics_publishes_counters_topics_and_task_errors():
    node = make_node('diag_under_test')
    observer = make_node()
    try:
        counts = {'received': 0, 'rejected': 0}
        diag = NodeDiagnostics(node, counts, period=0.2)

        def broken(stat):
            raise RuntimeError('boom')
        diag.add('broken', broken)
        arrays = []
        observer.create_subscription(DiagnosticArray, '/diagnostics', arrays.append, 10)
        assert spin_until([node], lambda: observer.count_publishers('/diagnostics') > 0, 10)
        spin_until([observer], lambda: False, 0.5)
        counts['received'] += 3
        counts['rejected'] += 1
        for _ in range(3):
            diag.tick('corrected_pose', node.get_clock().now().to_msg())
        diag.force_update()

        def seen():
            return any(s.name == 'diag_under_test: counters' and s.level == DiagnosticStatus.WARN
                       for a in arrays for s in a.status)
        assert spin_until([observer], seen, 10), [s.name for a in arrays for s in a.status]
        statuses = {s.name: s for a in arrays for s in a.status}
        counters = statuses['diag_under_test: counters']
        assert 'rejected +1' in counters.message
        assert {kv.key: kv.value for kv in counters.values}['received'] == '3'
        topics = {kv.key: kv.value for kv in statuses['diag_under_test: topics'].values}
        assert topics['corrected_pose count'] == '3'
        assert float(topics['corrected_pose stamp age max [s]']) < 5.0
        assert statuses['diag_under_test: broken'].level == DiagnosticStatus.ERROR
        assert 'boom' in statuses['diag_under_test: broken'].message
        # the timer keeps publishing; with no new rejection the counters go back to OK
        n = len(arrays)
        assert spin_until([node], lambda: diag.published >= 3, 5)
        assert spin_until([observer], lambda: len(arrays) > n, 5)
        last = {s.name: s for s in arrays[-1].status}
        assert last['diag_under_test: counters'].level == DiagnosticStatus.OK
    finally:
        shutdown_node(node)
        shutdown_node(observer)


class FakeTrackStatus:
    """The fields of stereo_manip_msgs/TrackStatus that the diagnostics read."""

    ACQUIRING, TRACKING, LOST, STATIC = 0, 1, 2, 3

    def __init__(self, name, state, reason=''):
        self.object_name, self.state, self.reason = name, state, reason
        self.quality, self.inlier_fraction = 0.25, 0.5


@pytest.mark.ros
def test_follow_counts_published_and_received_messages_and_track_states():
    from geometry_msgs.msg import PoseStamped
    node = make_node('follower')
    try:
        pub = node.create_publisher(PoseStamped, 'objects/peg/pose', 10)
        got = []
        node.create_subscription(PoseStamped, 'objects/peg/pose', got.append, 10)
        diag = NodeDiagnostics(node, {'received': 0})           # follows both at construction
        assert set(diag.topics) == {'objects/peg/pose'}
        for _ in range(3):
            msg = PoseStamped()
            msg.header.stamp = node.get_clock().now().to_msg()
            pub.publish(msg)
        assert spin_until(node, lambda: len(got) == 3, 10)
        # 3 published + 3 received, both ticked under the topic's name
        assert diag.topics['objects/peg/pose'].count == 6
        stats = {s.name: s for s in diag.run_tasks()}
        v = dict(stats['follower: topics'].values)
        assert v['objects/peg/pose count'] == '6'
        assert float(v['objects/peg/pose stamp age max [s]']) < 10.0
        diag._observe('objects/peg/status', FakeTrackStatus('peg', FakeTrackStatus.LOST,
                                                            'occluded'))
        tracks = {s.name: s for s in diag.run_tasks()}['follower: tracks']
        assert tracks.level == WARN and 'peg LOST' in tracks.message
        assert dict(tracks.values)['peg reason'] == 'occluded'
        diag._observe('objects/peg/status', FakeTrackStatus('peg', FakeTrackStatus.TRACKING))
        tracks = {s.name: s for s in diag.run_tasks()}['follower: tracks']
        assert tracks.level == OK and dict(tracks.values)['peg state'] == 'TRACKING'
        with pytest.raises(TypeError):
            diag.follow(object())
    finally:
        shutdown_node(node)
