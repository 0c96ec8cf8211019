"""
TF helpers.

PoseStamped <-> TransformStamped, broadcasters' wire format and QoS, the listener's chain
composition against poses composed by hand.
"""

from geometry_msgs.msg import PoseStamped, TransformStamped
import numpy as np
import pytest
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, ReliabilityPolicy
from std_msgs.msg import Header
from stereo_manip_tools.conversions import matrix_to_pose, ns_to_stamp, \
    pose_stamped_to_transform_stamped, transform_stamped_to_matrix
from stereo_manip_tools.testing import make_node, shutdown_node, spin_until
from stereo_manip_tools.tf import FrameLookupError, PoseTfPublisher, \
    StaticTransformBroadcaster, TransformBroadcaster, TransformListener
from stereo_manip_tools.transforms import make_transform, rotation_about_axis
from tf2_msgs.msg import TFMessage


def random_pose(rng: np.random.Generator) -> np.ndarray:
    return make_transform(rotation_about_axis(rng.normal(size=3), rng.uniform(-np.pi, np.pi)),
                          rng.uniform(-1, 1, 3))


def test_tf2_msgs_interface_is_the_upstream_definition():
    # the stand-in (or a real install's) TFMessage: one field, a TransformStamped sequence
    assert TFMessage.get_fields_and_field_types() == {
        'transforms': 'sequence<geometry_msgs/TransformStamped>'}


def test_pose_to_transform_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        T = random_pose(rng)
        pose = PoseStamped(header=Header(stamp=ns_to_stamp(123456789012), frame_id='cam'),
                           pose=matrix_to_pose(T))
        t = pose_stamped_to_transform_stamped(pose, 'peg')
        assert (t.header.frame_id, t.child_frame_id) == ('cam', 'peg')
        T2, stamp, parent, child = transform_stamped_to_matrix(t)
        assert np.allclose(T2, T, atol=1e-12)
        assert (stamp, parent, child) == (123456789012, 'cam', 'peg')


def test_bad_poses_raise():
    pose = PoseStamped(header=Header(frame_id='cam'))
    pose.pose.orientation.w = 0.0
    with pytest.raises(ValueError):
        pose_stamped_to_transform_stamped(pose, 'peg')       # zero quaternion
    pose.pose.orientation.w = 1.0
    with pytest.raises(ValueError):
        pose_stamped_to_transform_stamped(pose, '')
    t = TransformStamped()
    t.transform.rotation.w = 1.0
    t.transform.translation.x = float('nan')
    with pytest.raises(ValueError):
        transform_stamped_to_matrix(t)


@pytest.mark.ros
def test_broadcasters_and_listener_compose_chains():
    """
    Compose world -(static)-> cam -> peg, cam -> hole through broadcasters and a listener.

    The listener's peg-in-hole equals the product of the matrices, the static one reaches a late
    listener, bad input is refused.
    """
    rng = np.random.default_rng(7)
    T_w_c, T_c_p, T_c_h = (random_pose(rng) for _ in range(3))
    talker = make_node()
    listener_node = make_node()
    try:
        static = StaticTransformBroadcaster(talker)
        dynamic = TransformBroadcaster(talker)
        static.send_transform(pose_stamped_to_transform_stamped(
            PoseStamped(header=Header(frame_id='world'), pose=matrix_to_pose(T_w_c)), 'cam'))
        info = talker.get_publishers_info_by_topic('/tf_static')[0].qos_profile
        assert info.durability == DurabilityPolicy.TRANSIENT_LOCAL
        assert info.reliability == ReliabilityPolicy.RELIABLE
        # the listener starts after the static transform was sent (transient local)
        listener = TransformListener(listener_node)
        header = Header(stamp=ns_to_stamp(5_000_000_000), frame_id='cam')
        poses = [(PoseStamped(header=header, pose=matrix_to_pose(T_c_p)), 'peg'),
                 (PoseStamped(header=header, pose=matrix_to_pose(T_c_h)), 'hole')]
        hook = PoseTfPublisher(talker)
        ok = False
        for _ in range(100):
            hook.send(poses)
            spin_until(listener_node, lambda: False, 0.05)
            if listener.can_transform('hole', 'peg') and listener.can_transform('world', 'peg'):
                ok = True
                break
        assert ok, f'frames seen: {listener.frames()}'
        T_h_p, stamp = listener.lookup('hole', 'peg')
        assert np.allclose(T_h_p, np.linalg.inv(T_c_h) @ T_c_p, atol=1e-9)
        assert stamp == 5_000_000_000
        T_w_p, _ = listener.lookup('world', 'peg')
        assert np.allclose(T_w_p, T_w_c @ T_c_p, atol=1e-9)
        with pytest.raises(FrameLookupError):
            listener.lookup('world', 'nowhere')
        with pytest.raises(ValueError):
            dynamic.send_transform(TransformStamped(child_frame_id='x'))   # no parent
        # publish_tf false: nothing more is sent
        sent = hook.sent
        talker.set_parameters([Parameter('publish_tf', value=False)])
        hook.send(poses)
        assert hook.sent == sent
        # a NaN pose is counted, not raised
        bad = PoseStamped(header=header)
        bad.pose.orientation.w = float('nan')
        talker.set_parameters([Parameter('publish_tf', value=True)])
        hook.send([(bad, 'peg')])
        assert hook.errors == 1
    finally:
        shutdown_node(talker)
        shutdown_node(listener_node)


@pytest.mark.ros
def test_camera_mount_parameters():
    """
    The mount is published as declared.

    a malformed one is logged and left out (no crash); no parent, no transform.
    """
    from rclpy import create_node
    from stereo_manip_tools.tf import BODY_TO_OPTICAL_QUATERNION, publish_camera_mount
    anchor = make_node()
    try:
        cases = [([Parameter('camera_mount_parent', value='base_link'),
                   Parameter('camera_mount_pose',
                             value=[0.1, 0.2, 0.3, *BODY_TO_OPTICAL_QUATERNION])], True),
                 ([Parameter('camera_mount_parent', value='base_link'),
                   Parameter('camera_mount_pose', value=[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])],
                  False),
                 ([Parameter('camera_mount_parent', value='base_link'),
                   Parameter('camera_frame', value='base_link')], False),
                 ([], False)]
        for k, (overrides, published) in enumerate(cases):
            node = create_node(f'mount_{k}', context=anchor.context,
                               parameter_overrides=overrides)
            try:
                assert (publish_camera_mount(node) is not None) == published, overrides
            finally:
                node.destroy_node()
        # the body -> optical rotation: optical z (forward) = body x, optical x (right) = -body y
        from stereo_manip_tools.transforms import matrix_from_quaternion
        R = matrix_from_quaternion(BODY_TO_OPTICAL_QUATERNION)
        assert np.allclose(R[:, 2], [1, 0, 0]) and np.allclose(R[:, 0], [0, -1, 0])
        assert np.allclose(R[:, 1], [0, 0, -1])
    finally:
        shutdown_node(anchor)
