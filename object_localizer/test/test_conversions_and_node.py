"""Message conversions and the node in-process (rclpy, no separate process)."""

import numpy as np
from object_localizer.conversions import cloud_xyz, track_status
from object_localizer.evaluation import sample_visible_surface
from object_localizer.tracking import PoseQuality, TrackState
import pytest
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
from stereo_manip_msgs.msg import TrackStatus
from stereo_manip_tools.conversions import ns_to_stamp, pointcloud2_to_array, xyz_to_pointcloud2
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.transforms import make_transform, rotation_about_axis


def test_cloud_xyz_fast_path_equals_the_shared_reader():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(500, 3)).astype(np.float32)
    P[7] = np.nan
    msg = xyz_to_pointcloud2(P, rgb=rng.integers(0, 255, (500, 3)))   # x y z rgb, step 16
    got = cloud_xyz(msg)
    assert got.dtype == np.float32 and got.shape == (500, 3)
    assert np.array_equal(got, P, equal_nan=True)          # NaN rows kept (organised clouds)
    finite = pointcloud2_to_array(msg)
    assert np.allclose(got[np.isfinite(got[:, 2])], finite)


def test_cloud_xyz_other_layouts_and_bad_data():
    P = np.arange(30, dtype=np.float64).reshape(10, 3)
    fields = [PointField(name=n, offset=8 * i, datatype=PointField.FLOAT64, count=1)
              for i, n in enumerate('xyz')]
    msg = PointCloud2(height=1, width=10, point_step=24, row_step=240, fields=fields,
                      data=P.tobytes())
    assert np.allclose(cloud_xyz(msg), P)                   # float64: the shared reader
    short = xyz_to_pointcloud2(P)
    short.data = bytes(short.data)[:50]
    with pytest.raises(ValueError, match='bytes'):
        cloud_xyz(short)
    no_z = PointCloud2(height=1, width=10, point_step=16, fields=fields[:2], data=b'\0' * 160)
    with pytest.raises(ValueError, match="no field 'z'"):
        cloud_xyz(no_z)


def test_track_status_fields():
    q = PoseQuality(inlier_fraction=0.9, visible_residual=0.0007, prediction_error=0.002,
                    quality=0.8, passed=True)
    header = Header(frame_id='cam', stamp=ns_to_stamp(5))
    msg = track_status(header, 'peg', TrackState.TRACKING, q, 'tracking', 0.0123)
    assert msg.state == TrackStatus.TRACKING and msg.object_name == 'peg'
    assert msg.header == header and msg.reason == 'tracking'
    assert msg.cpu_time == pytest.approx(0.0123)
    assert msg.inlier_fraction == pytest.approx(0.9) and msg.quality == pytest.approx(0.8)
    assert msg.visible_residual == pytest.approx(0.0007)
    none = track_status(header, 'peg', TrackState.ACQUIRING, None, 'acquisition failed')
    assert none.quality == 0.0 and none.state == TrackStatus.ACQUIRING


def test_node_builds_segment_and_path_only_for_subscribers(ros_node):
    """
    The node builds the segment and the path only for subscribers.

    In-process node: with nobody on objects/<name>/cloud and track, neither is built; with a
    subscriber both are published. A status is published for every processed cloud.
    """
    from rclpy.parameter import Parameter
    from object_localizer.localizer_node import ObjectLocalizerNode
    from stereo_manip_tools.testing import spin_until

    arm = load_obj(find_model('link_arm'))
    T = make_transform(rotation_about_axis([0.2, 1.0, 0.1], 0.9), [0.03, -0.02, 0.7])
    points = sample_visible_surface(arm, T, 8000, seed=7)
    node = ObjectLocalizerNode(context=ros_node.context, parameter_overrides=[
        Parameter('models', value=['link_arm'])])
    built = {'cloud': 0, 'track': 0}
    for kind, pubs in (('cloud', node.cloud_pubs), ('track', node.track_pubs)):
        original = pubs['link_arm'].publish

        def counting(msg, kind=kind, original=original):
            built[kind] += 1
            original(msg)
        pubs['link_arm'].publish = counting
    statuses = []
    ros_node.create_subscription(TrackStatus, '/objects/link_arm/status', statuses.append, 10)
    try:
        for k in range(2):
            header = Header(frame_id='stereo_left_optical', stamp=ns_to_stamp(k * 100_000_000))
            n0 = len(statuses)
            node._on_cloud(xyz_to_pointcloud2(points, header))
            assert spin_until([ros_node, node], lambda: len(statuses) > n0, 60)
            if k == 0:
                assert built == {'cloud': 0, 'track': 0}
                ros_node.create_subscription(PointCloud2, '/objects/link_arm/cloud',
                                             lambda m: None, 10)
                from nav_msgs.msg import Path
                ros_node.create_subscription(Path, '/objects/link_arm/track', lambda m: None,
                                             10)
                spin_until([ros_node, node], lambda: node.cloud_pubs['link_arm']
                           .get_subscription_count() > 0 and node.track_pubs['link_arm']
                           .get_subscription_count() > 0, 10)
        # (published by the worker thread just after the status)
        assert spin_until([ros_node, node], lambda: built == {'cloud': 1, 'track': 1}, 10), built
        assert [s.state for s in statuses] == [TrackStatus.TRACKING] * 2
        assert node.counts['processed'] == 2 and node.counts['published'] == 2
    finally:
        node.destroy_node()


def _two_bricks_node(ros_node, **parameters):
    """
    Return meshes, true poses and an in-process node for the identical bricks.

    link_base and link_arm at fixed poses 0.6 m in front of the camera; the node gets their
    true poses as hints (``initial_poses``) and ``parameters`` as overrides.
    """
    from rclpy.parameter import Parameter
    from object_localizer.localizer_node import ObjectLocalizerNode
    from stereo_manip_tools.transforms import quaternion_from_matrix

    meshes = {n: load_obj(find_model(n)) for n in ('link_base', 'link_arm')}
    truth = {'link_base': make_transform(rotation_about_axis([1, 0, 0], 2.2), [-0.06, 0, 0.6]),
             'link_arm': make_transform(rotation_about_axis([1, 0.2, 0], 2.0),
                                        [0.08, 0.02, 0.62])}
    hints = []
    for n in ('link_base', 'link_arm'):
        hints += list(truth[n][:3, 3]) + list(quaternion_from_matrix(truth[n][:3, :3]))
    node = ObjectLocalizerNode(context=ros_node.context, parameter_overrides=[
        Parameter('models', value=['link_base', 'link_arm']),
        Parameter('initial_poses', value=[float(v) for v in hints])] + [
        Parameter(k, value=v) for k, v in parameters.items()])
    return meshes, truth, node


def test_tracked_objects_are_published_before_a_lost_ones_search(ros_node):
    """
    A lost track's global search waits for the objects that still track.

    In-process node with link_base and link_arm (identical bricks), both verified from hints on
    the first cloud and tracked on the second. On the third, link_base has jumped 15 cm: its
    track is lost, and its search runs only after link_arm's pose is published (a search takes
    seconds; it must not delay a tracked pose), with link_arm verified in this cloud among the
    search's `others`.
    """
    meshes, truth, node = _two_bricks_node(ros_node)
    events = []
    searched_with = []
    for name, tracker in node.trackers.items():
        original = tracker.update

        def update(*a, _orig=original, _name=name, **kw):
            events.append((_name, 'update', kw.get('reacquire', True)))
            return _orig(*a, **kw)
        tracker.update = update

        def no_candidates(model, points, seed, explained=None, _name=name):
            searched_with.append([m.name for m, _ in node.trackers[_name]._others])
            events.append((_name, 'search', None))
            return []
        tracker.acquirer = no_candidates
        original_publish = node.pose_pubs[name].publish

        def publish(msg, _orig=original_publish, _name=name):
            events.append((_name, 'pose', None))
            _orig(msg)
        node.pose_pubs[name].publish = publish
    jumped = make_transform(np.eye(3), [0.15, 0.0, 0.0]) @ truth['link_base']
    try:
        for k, poses in enumerate((truth, truth, {**truth, 'link_base': jumped})):
            cloud = np.vstack([sample_visible_surface(meshes[n], T, 8000, seed=10 * k + i)
                               for i, (n, T) in enumerate(poses.items())])
            header = Header(frame_id='stereo_left_optical', stamp=ns_to_stamp(k * 100_000_000))
            events.clear()
            node._process(xyz_to_pointcloud2(cloud, header))
            if k < 2:
                assert [e for e in events if e[1] == 'pose'] == [('link_base', 'pose', None),
                                                                 ('link_arm', 'pose', None)]
        assert events == [('link_base', 'update', False), ('link_arm', 'update', False),
                          ('link_arm', 'pose', None), ('link_base', 'update', True),
                          ('link_base', 'search', None)], events
        assert searched_with == [['link_arm']]
        assert node.trackers['link_base'].state == TrackState.LOST
        assert node.trackers['link_arm'].state == TrackState.TRACKING
        assert node.counts['lost'] == 1 and node.counts['published'] == 5
    finally:
        node.destroy_node()


def _lose_link_base_with_slow_searches(meshes, truth, node):
    """
    Five clouds; link_base is gone from the third on, and its searches find nothing.

    Each search spends 0.3 s of CPU. Return ({name: (pose, reason)} per cloud, search count);
    link_arm's pose is checked against the truth in every cloud.
    """
    from object_localizer.evaluation import add_s

    searches = []

    def search(model, points, seed, explained=None):  # finds nothing in 0.3 s of CPU
        import time
        searches.append(seed)
        t0 = time.process_time()
        while time.process_time() - t0 < 0.3:
            pass
        return []
    node.trackers['link_base'].acquirer = search
    outcomes, per_cloud = [], []
    original = node._publish

    def publish(name, result, *a):
        outcomes.append((name, result.pose, result.reason))
        original(name, result, *a)
    node._publish = publish
    for k in range(5):
        poses = truth if k < 2 else {'link_arm': truth['link_arm']}
        cloud = np.vstack([sample_visible_surface(meshes[n], T, 8000, seed=10 * k + i)
                           for i, (n, T) in enumerate(poses.items())])
        header = Header(frame_id='stereo_left_optical', stamp=ns_to_stamp(k * 100_000_000))
        outcomes.clear()
        node._process(xyz_to_pointcloud2(cloud, header))
        got = {n: (p, r) for n, p, r in outcomes}
        pose = got['link_arm'][0]
        assert pose is not None and add_s(pose, truth['link_arm'],
                                          node.trackers['link_arm'].model.points) < 0.001
        per_cloud.append(got)
    return per_cloud, len(searches)


def test_global_searches_are_deferred_beyond_their_cpu_share(ros_node):
    """
    While an object tracks, a lost one's global searches take at most their CPU share.

    link_base and link_arm verified from hints and tracked; then link_base is gone for three
    clouds. The first search runs (saved-up credit 0.1 s), it spends 0.3 s; with a share of 5 %
    of the wall time the next clouds defer the search (status reason says so, counted) while
    link_arm is still published every cloud. The tracked pose stays right (ground truth).
    """
    meshes, truth, node = _two_bricks_node(ros_node, search_cpu_share=0.05,
                                           search_cpu_burst=0.1)
    try:
        per_cloud, searches = _lose_link_base_with_slow_searches(meshes, truth, node)
        for got in per_cloud[3:]:
            assert got['link_base'][0] is None
            assert 'global search deferred' in got['link_base'][1], got['link_base'][1]
        assert searches == 1
        assert node.counts['searches_deferred'] == 2
    finally:
        node.destroy_node()


def test_a_static_object_does_not_defer_the_searches(ros_node):
    """
    The same with link_arm declared static: it is held, it has no camera rate to keep.

    Every cloud searches for link_base (a restart with the hole block found first waited for
    the credit), and link_arm is still published, right, in every cloud.
    """
    meshes, truth, node = _two_bricks_node(ros_node, search_cpu_share=0.05,
                                           search_cpu_burst=0.1, static_objects=['link_arm'])
    try:
        per_cloud, searches = _lose_link_base_with_slow_searches(meshes, truth, node)
        assert searches == 3, [got['link_base'][1] for got in per_cloud]
        assert node.counts['searches_deferred'] == 0
    finally:
        node.destroy_node()


def test_camera_from_camera_info_reads_the_rectified_projection():
    """The acquisition camera is P's intrinsics and the image size; an unset P is refused."""
    from object_localizer.conversions import camera_from_camera_info
    from object_localizer.verification import PinholeCamera
    from sensor_msgs.msg import CameraInfo

    msg = CameraInfo(width=640, height=480)
    msg.p = [525.0, 0.0, 319.5, -52.5, 0.0, 526.0, 239.5, 0.0, 0.0, 0.0, 1.0, 0.0]
    assert camera_from_camera_info(msg) == PinholeCamera(525.0, 526.0, 319.5, 239.5, 640, 480)
    with pytest.raises(ValueError, match='P not set'):
        camera_from_camera_info(CameraInfo(width=640, height=480))
    msg.width = 0
    with pytest.raises(ValueError, match='image size'):
        camera_from_camera_info(msg)
