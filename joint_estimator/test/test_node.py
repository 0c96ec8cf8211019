"""joint_estimator_node: in-process (rclpy) and as an installed executable (own process)."""

from geometry_msgs.msg import PoseStamped
from joint_estimator.common import JointType
from joint_estimator.joint_estimator_node import JointEstimatorNode
from joint_estimator.synthetic import add_noise, random_joint_motion
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from std_msgs.msg import Header
from stereo_manip_msgs.msg import JointEstimate
from stereo_manip_msgs.srv import EstimateJoint
from stereo_manip_tools.conversions import matrices_to_path, matrix_to_pose, ns_to_stamp, \
    path_to_matrices, pose_to_matrix
from stereo_manip_tools.testing import call_service, spin_until, start_executable
from visualization_msgs.msg import Marker

SP, SR = 0.001, np.deg2rad(1.0)


def _door(n=40, seed=0):
    rng = np.random.default_rng(seed)
    g = random_joint_motion(JointType.REVOLUTE, n, rng)
    return g, add_noise(g.poses, SP, SR, rng)


def _stamped(T, stamp_ns, frame):
    return PoseStamped(header=Header(stamp=ns_to_stamp(int(stamp_ns)), frame_id=frame),
                       pose=matrix_to_pose(T))


@pytest.fixture
def estimator(ros_node):
    """Provide a JointEstimatorNode in the ros_node's context, relative input."""
    node = JointEstimatorNode(context=ros_node.context, parameter_overrides=[
        Parameter('input_mode', value='relative'), Parameter('min_poses', value=20),
        Parameter('estimate_every', value=10), Parameter('sigma_position', value=SP),
        Parameter('sigma_rotation', value=float(SR))])
    yield node
    node.destroy_node()


def _spin_both(nodes, predicate, timeout=20.0):
    return spin_until(nodes, predicate, timeout)


@pytest.mark.ros
def test_streaming_relative_poses_publish_a_revolute_estimate(ros_node, estimator):
    g, noisy = _door()
    got, corrected, markers = [], [], []
    ros_node.create_subscription(JointEstimate, 'joint_estimate', got.append, 10)
    ros_node.create_subscription(PoseStamped, 'corrected_pose', corrected.append, 10)
    ros_node.create_subscription(Marker, 'joint_marker', markers.append, 10)
    pub = ros_node.create_publisher(PoseStamped, 'relative_pose', 10)
    assert _spin_both([ros_node, estimator], lambda: pub.get_subscription_count() > 0)
    for i, T in enumerate(noisy):
        pub.publish(_stamped(T, (i + 1) * 10 ** 8, 'door_frame'))
        _spin_both([ros_node, estimator], lambda: False, timeout=0.02)
    assert _spin_both([ros_node, estimator], lambda: len(got) >= 3 and len(markers) >= 3)
    msg = got[-1]
    # the marker's line lies on the true axis (within the estimate's accuracy)
    ends = [np.array([q.x, q.y, q.z]) for q in markers[-1].points]
    assert markers[-1].type == Marker.LINE_LIST and markers[-1].header.frame_id == 'door_frame'
    for e in ends:
        d = e - g.point_in_b
        assert np.linalg.norm(d - g.axis_in_b * (d @ g.axis_in_b)) < 0.02
    assert msg.joint_type == JointEstimate.REVOLUTE
    assert msg.header.frame_id == 'door_frame'
    axis = np.array([msg.axis_in_b.x, msg.axis_in_b.y, msg.axis_in_b.z])
    assert np.degrees(np.arccos(min(1.0, abs(axis @ g.axis_in_b)))) < 2.0
    assert msg.sample_count == 40 and msg.outlier_count == 0
    assert JointEstimate.REVOLUTE in list(msg.candidate_types)
    assert len(msg.candidate_types) == len(msg.candidate_scores)
    assert 'revolute selected' in msg.status and '0 poses rejected' in msg.status
    assert corrected
    for c in corrected:                       # the newest pose of each window, corrected
        i = (c.header.stamp.sec * 10 ** 9 + c.header.stamp.nanosec) // 10 ** 8 - 1
        T_c = pose_to_matrix(c.pose)
        assert np.linalg.norm(T_c[:3, 3] - g.poses[i, :3, 3]) < 0.01


@pytest.mark.ros
def test_bad_poses_are_counted_and_the_node_keeps_running(ros_node, estimator):
    _, noisy = _door()
    got = []
    ros_node.create_subscription(JointEstimate, 'joint_estimate', got.append, 10)
    pub = ros_node.create_publisher(PoseStamped, 'relative_pose', 10)
    assert _spin_both([ros_node, estimator], lambda: pub.get_subscription_count() > 0)
    bad = _stamped(noisy[0], 5, 'b')
    bad.pose.orientation.w = 0.0
    bad.pose.orientation.x = bad.pose.orientation.y = bad.pose.orientation.z = 0.0
    pub.publish(bad)                                              # zero quaternion
    _spin_both([ros_node, estimator], lambda: False, timeout=0.05)
    nan = _stamped(noisy[0], 6, 'b')
    nan.pose.position.x = float('nan')
    pub.publish(nan)                                              # NaN position
    _spin_both([ros_node, estimator], lambda: False, timeout=0.05)
    scaled = _stamped(noisy[0], 7, 'b')           # a quaternion of norm 2: malformed (#16 fuzz)
    o = scaled.pose.orientation
    o.x, o.y, o.z, o.w = 2.0 * o.x, 2.0 * o.y, 2.0 * o.z, 2.0 * o.w
    pub.publish(scaled)
    _spin_both([ros_node, estimator], lambda: False, timeout=0.05)
    for i, T in enumerate(noisy):
        pub.publish(_stamped(T, (i + 1) * 10 ** 8, 'b'))
        _spin_both([ros_node, estimator], lambda: False, timeout=0.02)
    # a stamp slightly behind the newest (reordering, within stamp_reset_threshold)
    pub.publish(_stamped(noisy[0], 40 * 10 ** 8 - 10 ** 7, 'b'))
    assert _spin_both([ros_node, estimator],
                      lambda: estimator.counts['rejected'] >= 4 and len(got) >= 2)
    assert estimator.counts['rejected'] == 4 and estimator.counts['resets'] == 0
    assert got[-1].joint_type == JointEstimate.REVOLUTE


@pytest.mark.ros
def test_stamps_jumping_back_reset_the_window_and_estimates_resume(ros_node, estimator):
    """
    A source restart / bag loop (#16): the stamps start again from the beginning.

    The window is cleared once per event (not every later pose rejected) and estimates resume from
    the new poses only.
    """
    g, noisy = _door()
    got = []
    ros_node.create_subscription(JointEstimate, 'joint_estimate', got.append, 10)
    pub = ros_node.create_publisher(PoseStamped, 'relative_pose', 10)
    assert _spin_both([ros_node, estimator], lambda: pub.get_subscription_count() > 0)
    for loop in range(2):                 # the same 40 poses twice, stamps restarting
        for i, T in enumerate(noisy):
            pub.publish(_stamped(T, (i + 1) * 10 ** 8, 'b'))
            _spin_both([ros_node, estimator], lambda: False, timeout=0.02)
        assert _spin_both([ros_node, estimator],
                          lambda: len(got) >= 3 * (loop + 1)), (loop, len(got))
    assert estimator.counts['resets'] == 1 and estimator.counts['rejected'] == 0
    counts = [m.sample_count for m in got]
    # first pass: windows of 20, 30, 40; after the restart: 20, 30, 40 again (not 40+)
    assert counts == [20, 30, 40, 20, 30, 40], counts
    last = got[-1]
    assert last.joint_type == JointEstimate.REVOLUTE and '1 source restarts' in last.status
    axis = np.array([last.axis_in_b.x, last.axis_in_b.y, last.axis_in_b.z])
    assert np.degrees(np.arccos(min(1.0, abs(axis @ g.axis_in_b)))) < 2.0


@pytest.mark.ros
def test_two_link_stamps_jumping_back_reset_the_pairing(ros_node):
    node = JointEstimatorNode(context=ros_node.context, parameter_overrides=[
        Parameter('min_poses', value=20), Parameter('estimate_every', value=20),
        Parameter('joint_type', value='revolute')])
    try:
        g, noisy = _door(20, seed=4)
        link_b = np.tile(np.eye(4), (20, 1, 1))
        link_b[:, :3, 3] = [0.1, 0.0, 1.0]
        link_a = link_b @ noisy
        got = []
        ros_node.create_subscription(JointEstimate, 'joint_estimate', got.append, 10)
        pa = ros_node.create_publisher(PoseStamped, 'link_a_pose', 10)
        pb = ros_node.create_publisher(PoseStamped, 'link_b_pose', 10)
        assert _spin_both([ros_node, node], lambda: pa.get_subscription_count() > 0
                          and pb.get_subscription_count() > 0)
        for loop in range(2):
            for i in range(20):
                pb.publish(_stamped(link_b[i], (i + 1) * 10 ** 8, 'cam'))
                pa.publish(_stamped(link_a[i], (i + 1) * 10 ** 8, 'cam'))
                _spin_both([ros_node, node], lambda: False, timeout=0.01)
            assert _spin_both([ros_node, node], lambda: len(got) >= loop + 1), loop
        assert node.counts['resets'] == 1
        assert [m.sample_count for m in got] == [20, 20]
        assert got[-1].joint_type == JointEstimate.REVOLUTE
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_two_link_input_is_paired_by_stamp(ros_node):
    node = JointEstimatorNode(context=ros_node.context, parameter_overrides=[
        Parameter('min_poses', value=30), Parameter('estimate_every', value=30),
        Parameter('joint_type', value='revolute'), Parameter('link_a_frame', value='lid'),
        Parameter('link_b_frame', value='box')])
    try:
        g, noisy = _door(30, seed=3)
        rng = np.random.default_rng(1)
        from scipy.spatial.transform import Rotation
        link_b = np.tile(np.eye(4), (30, 1, 1))
        link_b[:, :3, :3] = Rotation.random(30, random_state=rng).as_matrix()
        link_b[:, :3, 3] = rng.uniform(-1, 1, (30, 3))
        link_a = link_b @ noisy
        got = []
        ros_node.create_subscription(JointEstimate, 'joint_estimate', got.append, 10)
        pa = ros_node.create_publisher(PoseStamped, 'link_a_pose', 10)
        pb = ros_node.create_publisher(PoseStamped, 'link_b_pose', 10)
        assert _spin_both([ros_node, node], lambda: pa.get_subscription_count() > 0
                          and pb.get_subscription_count() > 0)
        for i in range(30):
            pb.publish(_stamped(link_b[i], (i + 1) * 10 ** 8, 'world'))
            pa.publish(_stamped(link_a[i], (i + 1) * 10 ** 8 + 1000, 'world'))
            _spin_both([ros_node, node], lambda: False, timeout=0.01)
        assert _spin_both([ros_node, node], lambda: len(got) >= 1)
        msg = got[-1]
        assert msg.link_a_frame == 'lid' and msg.header.frame_id == 'box'
        assert msg.joint_type == JointEstimate.REVOLUTE and msg.sample_count == 30
        axis = np.array([msg.axis_in_b.x, msg.axis_in_b.y, msg.axis_in_b.z])
        assert np.degrees(np.arccos(min(1.0, abs(axis @ g.axis_in_b)))) < 2.0
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_parameters_are_validated(estimator):
    bad = estimator.set_parameters([Parameter('joint_type', value='hinge')])[0]
    assert not bad.successful and 'joint_type must be one of' in bad.reason
    assert not estimator.set_parameters([Parameter('sigma_position', value=-1.0)])[0].successful
    bad = estimator.set_parameters([Parameter('marker_normal_axis', value='w')])[0]
    assert not bad.successful and 'marker_normal_axis' in bad.reason
    assert not estimator.set_parameters([Parameter('window_size', value=10)])[0].successful
    assert estimator.set_parameters([Parameter('joint_type', value='prismatic')])[0].successful


def _call(node, server_node, request, timeout=20.0):
    nodes = [node] + ([server_node] if server_node is not None else [])
    return call_service(nodes, EstimateJoint, 'estimate_joint', request, timeout)


@pytest.mark.ros
def test_service_batch_estimate_and_bad_requests(ros_node, estimator):
    g, noisy = _door(50, seed=5)
    stamps = (np.arange(50) + 1) * 10 ** 7
    req = EstimateJoint.Request(link_a=matrices_to_path(noisy, 'base', stamps),
                                joint_type=EstimateJoint.Request.AUTO)
    res = _call(ros_node, estimator, req)
    assert res.success, res.message
    assert res.estimate.joint_type == JointEstimate.REVOLUTE
    # the honest part of the estimate reaches the service response
    assert len(res.coordinates) == 50 and np.all(np.diff(res.coordinates) * np.sign(
        res.coordinates[-1] - res.coordinates[0]) > -0.05)      # unwrapped, monotone motion
    assert res.estimate.inlier_coverage > 0.9 and not res.estimate.warnings
    assert 0 < res.estimate.axis_angle_std_in_b < np.deg2rad(2.0)
    assert not res.estimate.noise_estimated          # the fixture gives the noise levels
    T_c, s_c = path_to_matrices(res.corrected_track)
    np.testing.assert_array_equal(s_c, stamps)
    assert np.mean(np.linalg.norm(T_c[:, :3, 3] - g.poses[:, :3, 3], axis=1)) < np.mean(
        np.linalg.norm(noisy[:, :3, 3] - g.poses[:, :3, 3], axis=1))
    # too few poses
    res = _call(ros_node, estimator, EstimateJoint.Request(
        link_a=matrices_to_path(noisy[:1], 'base', stamps[:1]), joint_type=1))
    assert not res.success and 'at least 2 needed' in res.message
    # stamps out of order
    res = _call(ros_node, estimator, EstimateJoint.Request(
        link_a=matrices_to_path(noisy, 'base', stamps[::-1]), joint_type=255))
    assert not res.success and 'out of order' in res.message
    # mismatched two-link request
    res = _call(ros_node, estimator, EstimateJoint.Request(
        link_a=matrices_to_path(noisy, 'w', stamps),
        link_b=matrices_to_path(noisy[:10], 'w', stamps[:10]), joint_type=255))
    assert not res.success and 'link_b 10' in res.message
    # unknown joint type
    res = _call(ros_node, estimator, EstimateJoint.Request(
        link_a=matrices_to_path(noisy, 'base', stamps), joint_type=17))
    assert not res.success and 'joint_type 17' in res.message


@pytest.mark.process
def test_installed_executable_serves_the_estimate_service(ros_node):
    g, noisy = _door(40, seed=9)
    stamps = (np.arange(40) + 1) * 10 ** 7
    with start_executable('joint_estimator', 'joint_estimator_node',
                          ros_args=['-p', 'input_mode:=relative'],
                          observer=ros_node, wait_for_node='joint_estimator') as proc:
        res = _call(ros_node, None, EstimateJoint.Request(
            link_a=matrices_to_path(noisy, 'base', stamps), joint_type=255))
        assert res.success, proc.output()
        assert res.estimate.joint_type == JointEstimate.REVOLUTE
        # default: noise estimated from the data, near the true 1 mm / 1 deg
        assert res.estimate.noise_estimated
        assert 0.0005 < res.estimate.position_noise < 0.002
        assert np.deg2rad(0.5) < res.estimate.rotation_noise < np.deg2rad(2.0)
        # streaming through the process too
        got = []
        ros_node.create_subscription(JointEstimate, 'joint_estimate', got.append, 10)
        pub = ros_node.create_publisher(PoseStamped, 'relative_pose', 10)
        assert spin_until(ros_node, lambda: pub.get_subscription_count() > 0, 20)
        for i, T in enumerate(noisy):
            pub.publish(_stamped(T, stamps[i], 'base'))
            spin_until(ros_node, lambda: False, 0.03)
        assert spin_until(ros_node, lambda: len(got) >= 1, 30), proc.output()
        assert got[-1].joint_type == JointEstimate.REVOLUTE
    assert rclpy.ok(context=ros_node.context)
