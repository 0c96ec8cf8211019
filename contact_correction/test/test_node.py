"""contact_correction_node in-process and as an installed executable; the offline command."""


from contact_correction.contact_correction_node import ContactCorrectionNode
from contact_correction.trajectory import ContactCorrector
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
import numpy as np
import pytest
import rclpy
from rclpy.parameter import Parameter
from std_msgs.msg import Header
from stereo_manip_msgs.msg import ContactState
from stereo_manip_msgs.srv import CorrectTrajectory
from stereo_manip_tools.conversions import matrices_to_path, matrix_to_pose, ns_to_stamp, \
    path_to_matrices, pose_to_matrix
from stereo_manip_tools.testing import call_service, spin_until, start_executable, \
    wait_for_subscribers
from stereo_manip_tools.transforms import make_transform, rotation_about_axis

STATIC = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]


def noisy_insertion(n=12, seed=0, sigma_t=1e-3, sigma_r=np.deg2rad(0.5)):
    """Peg poses inside the shipped hole_block (identity pose), bottom 1-4 cm deep."""
    rng = np.random.default_rng(seed)
    out = []
    for z in np.linspace(-0.01, -0.04, n):
        w = rng.normal(size=3) * sigma_r
        out.append(make_transform(rotation_about_axis(w, np.linalg.norm(w)),
                                  np.array([0.0, 0.0, z]) + rng.normal(size=3) * sigma_t))
    return np.array(out)


def _stamped(T, stamp_ns, frame='world'):
    return PoseStamped(header=Header(stamp=ns_to_stamp(int(stamp_ns)), frame_id=frame),
                       pose=matrix_to_pose(T))


def _spin_both(nodes, predicate, timeout=20.0):
    return spin_until(nodes, predicate, timeout)


@pytest.fixture
def corrector(ros_node):
    node = ContactCorrectionNode(context=ros_node.context, parameter_overrides=[
        Parameter('moving_object', value='peg'), Parameter('fixed_object', value='hole_block'),
        Parameter('fixed_pose_static', value=STATIC), Parameter('tolerance', value=0.004),
        Parameter('penetration_tolerance', value=0.004), Parameter('recognition', value=False)])
    yield node
    node.destroy_node()


@pytest.mark.ros
def test_streaming_poses_are_corrected(ros_node, corrector):
    states, poses = [], []
    ros_node.create_subscription(ContactState, 'contact_state', states.append, 10)
    ros_node.create_subscription(PoseStamped, 'corrected_pose', poses.append, 10)
    pub = ros_node.create_publisher(PoseStamped, 'moving_pose', 10)
    assert _spin_both([ros_node, corrector], lambda: pub.get_subscription_count() > 0)
    obs = noisy_insertion(6, seed=1)
    bad = PoseStamped(header=Header(stamp=ns_to_stamp(1), frame_id='world'))
    bad.pose.orientation.w = 0.0            # zero quaternion: rejected, counted
    pub.publish(bad)
    for k, T in enumerate(obs):
        pub.publish(_stamped(T, (k + 2) * 10**7))
        _spin_both([ros_node, corrector], lambda: len(states) > k, 10)
    assert _spin_both([ros_node, corrector], lambda: len(states) >= 6 and len(poses) >= 6)
    assert corrector.counts['rejected'] == 1 and corrector.counts['received'] == 7
    for s, p, T in zip(states, poses, obs):
        assert s.corrected, s.status
        assert s.rotation_rank == 3 and s.header.frame_id == 'hole_block'
        assert len(s.free_translation) == 1 and abs(s.free_translation[0].z) == pytest.approx(1)
        assert s.max_contact_residual < 1e-6 and len(s.pairs) == 16
        Tc = pose_to_matrix(p.pose)
        assert np.allclose(Tc[:3, :3], np.eye(3), atol=1e-8)
        assert np.allclose(Tc[:2, 3], 0.0, atol=1e-8)
        assert Tc[2, 3] == pytest.approx(T[2, 3], abs=1e-12)     # free direction untouched
    assert '1 rejected' in states[-1].status


@pytest.mark.ros
def test_far_pose_and_parameters(ros_node, corrector):
    states = []
    ros_node.create_subscription(ContactState, 'contact_state', states.append, 10)
    pub = ros_node.create_publisher(PoseStamped, 'moving_pose', 10)
    assert _spin_both([ros_node, corrector], lambda: pub.get_subscription_count() > 0)
    pub.publish(_stamped(make_transform(np.eye(3), [0.0, 0.0, 0.5]), 10))
    assert _spin_both([ros_node, corrector], lambda: len(states) >= 1)
    assert not states[0].corrected and 'no contact' in states[0].status
    assert not corrector.set_parameters([Parameter('tolerance', value=-1.0)])[0].successful
    assert not corrector.set_parameters(
        [Parameter('moving_object', value='cube')])[0].successful       # read-only
    assert corrector.set_parameters([Parameter('optimal', value=False)])[0].successful


@pytest.mark.ros
def test_guarded_correction_is_counted_not_applied(ros_node):
    """
    Peg resting on the top face (beside the hole), then one frame 5 mm up.

    Without the evidence rule (``evidence_chi2`` 0) the hysteresis keeps the contact; the
    correction back down would be 5 sigma (stated 1 mm), beyond ``max_correction_sigma`` 4: not
    applied (no penetration to remove: the observation is passed through), counted, flagged.
    """
    node = ContactCorrectionNode(context=ros_node.context, parameter_overrides=[
        Parameter('moving_object', value='peg'), Parameter('fixed_object', value='hole_block'),
        Parameter('fixed_pose_static', value=STATIC), Parameter('evidence_chi2', value=0.0)])
    try:
        states, poses = [], []
        ros_node.create_subscription(ContactState, 'contact_state', states.append, 10)
        ros_node.create_subscription(PoseStamped, 'corrected_pose', poses.append, 10)
        pub = ros_node.create_publisher(PoseStamped, 'moving_pose', 10)
        assert _spin_both([ros_node, node], lambda: pub.get_subscription_count() > 0)
        track = [make_transform(np.eye(3), [0.05, 0.0, 0.0])] * 8 + \
            [make_transform(np.eye(3), [0.05, 0.0, 0.005])]
        for k, T in enumerate(track):
            pub.publish(_stamped(T, (k + 1) * 10**7))
            assert _spin_both([ros_node, node], lambda: len(states) > k and len(poses) > k, 10)
        assert all(st.corrected for st in states[:8])
        assert node.counts['guarded'] == 1
        assert not states[8].corrected and 'guard' in states[8].status
        assert '1 guarded' in states[8].status
        assert pose_to_matrix(poses[8].pose)[2, 3] == pytest.approx(0.005, abs=1e-9)
    finally:
        node.destroy_node()


@pytest.mark.ros
def test_smoothed_poses_come_lag_frames_late_with_their_headers(ros_node):
    """
    ``corrected_pose_smoothed``: the fixed-lag corrector's results, ``smoothing_lag`` late.

    The peg resting beside the hole, then 3 mm up (noise 0.5 mm / 0.5 deg): frame j's
    smoothed pose comes with frame j + 2 (lag 2), under frame j's header, and equals
    ``ContactCorrector(lag=2)``'s; the last two are published once no pose has come for
    ``smoothing_timeout``.
    """
    node = ContactCorrectionNode(context=ros_node.context, parameter_overrides=[
        Parameter('moving_object', value='peg'), Parameter('fixed_object', value='hole_block'),
        Parameter('fixed_pose_static', value=STATIC), Parameter('smoothing_lag', value=2),
        Parameter('smoothing_timeout', value=0.3)])
    try:
        smoothed, poses = [], []
        ros_node.create_subscription(PoseStamped, 'corrected_pose_smoothed', smoothed.append, 10)
        ros_node.create_subscription(PoseStamped, 'corrected_pose', poses.append, 10)
        pub = ros_node.create_publisher(PoseStamped, 'moving_pose', 10)
        assert _spin_both([ros_node, node], lambda: pub.get_subscription_count() > 0
                          and node.smoothed_pub.get_subscription_count() > 0)
        rng = np.random.default_rng(4)
        track = []
        for k in range(10):
            w = rng.normal(size=3) * np.deg2rad(0.5)
            up = 0.003 if k >= 7 else 0.0
            track.append(make_transform(rotation_about_axis(w, np.linalg.norm(w)),
                                        np.array([0.05, 0.0, up]) + rng.normal(size=3) * 5e-4))
        for k, T in enumerate(track):
            pub.publish(_stamped(T, (k + 1) * 10**7))
            assert _spin_both([ros_node, node], lambda: len(poses) > k
                              and len(smoothed) >= k - 1, 10)
            assert len(smoothed) == max(k - 1, 0)          # two frames late
        assert _spin_both([ros_node, node], lambda: len(smoothed) == len(track), 5.0)
        assert node.counts['smoothed'] == len(track)
        reference = ContactCorrector(node.moving, node.fixed, node._recognition(), lag=2,
                                     **node._options())
        expected = [r for T in track for _, r in reference.push(T, np.eye(4))]
        expected += [r for _, r in reference.flush()]
        for k, (msg, r) in enumerate(zip(smoothed, expected)):
            assert msg.header.stamp == ns_to_stamp((k + 1) * 10**7)
            assert msg.header.frame_id == 'world'
            assert np.allclose(pose_to_matrix(msg.pose), r.T_moving, atol=1e-9)
    finally:
        node.destroy_node()


def _call(node, server_node, request, timeout=30.0):
    nodes = [node] + ([server_node] if server_node is not None else [])
    return call_service(nodes, CorrectTrajectory, 'correct_trajectory', request, timeout)


@pytest.mark.ros
def test_service_corrects_a_track(ros_node, corrector):
    obs = noisy_insertion(10, seed=2)
    stamps = (np.arange(10) + 1) * 10**7
    req = CorrectTrajectory.Request(
        moving_object='peg', fixed_object='hole_block', optimal=True, tolerance=0.004,
        moving_track=matrices_to_path(obs, 'world', stamps),
        fixed_track=matrices_to_path(np.eye(4)[None], 'world', stamps[:1]))
    res = _call(ros_node, corrector, req)
    assert res.success, res.message
    T_c, s_c = path_to_matrices(res.corrected_track)
    np.testing.assert_array_equal(s_c, stamps)
    assert len(res.states) == 10 and all(s.corrected for s in res.states)
    assert np.allclose(T_c[:, :2, 3], 0.0, atol=1e-8)
    assert np.allclose(T_c[:, 2, 3], obs[:, 2, 3], atol=1e-12)
    # mismatched fixed track, unknown model
    bad = CorrectTrajectory.Request(moving_track=req.moving_track,
                                    fixed_track=matrices_to_path(np.stack([np.eye(4)] * 3),
                                                                 'world', [1, 2, 3]))
    res = _call(ros_node, corrector, bad)
    assert not res.success and 'give 1 or 10' in res.message
    bad = CorrectTrajectory.Request(moving_object='no_such_model', moving_track=req.moving_track,
                                    fixed_track=req.fixed_track)
    res = _call(ros_node, corrector, bad)
    assert not res.success and 'no_such_model' in res.message


@pytest.mark.process
def test_installed_executable_serves_and_streams(ros_node):
    obs = noisy_insertion(5, seed=3)
    stamps = (np.arange(5) + 1) * 10**7
    with start_executable('contact_correction', 'contact_correction_node',
                          ros_args=['-p', 'tolerance:=0.004'],
                          observer=ros_node, wait_for_node='contact_correction') as proc:
        res = _call(ros_node, None, CorrectTrajectory.Request(
            optimal=True, moving_track=matrices_to_path(obs, 'world', stamps),
            fixed_track=matrices_to_path(np.eye(4)[None], 'world', stamps[:1])))
        assert res.success, proc.output()
        assert all(s.corrected for s in res.states), [s.status for s in res.states]
        # streaming with a fixed_pose topic
        states, tracks = [], []
        ros_node.create_subscription(ContactState, 'contact_state', states.append, 10)
        ros_node.create_subscription(Path, 'corrected_track', tracks.append, 10)
        pub_f = ros_node.create_publisher(PoseStamped, 'fixed_pose', 10)
        pub_m = ros_node.create_publisher(PoseStamped, 'moving_pose', 10)
        assert wait_for_subscribers(ros_node, [pub_m, pub_f])
        pub_m.publish(_stamped(obs[0], stamps[0]))        # before any fixed pose: counted
        spin_until(ros_node, lambda: False, 0.3)
        pub_f.publish(_stamped(np.eye(4), stamps[0]))
        spin_until(ros_node, lambda: False, 0.3)
        for k in range(1, 5):
            pub_m.publish(_stamped(obs[k], stamps[k]))
            spin_until(ros_node, lambda: len(states) >= k, 5)
        assert spin_until(ros_node, lambda: len(states) >= 4, 20), proc.output()
        assert all(s.corrected for s in states)
        assert '1 without fixed pose' in states[-1].status
        assert spin_until(ros_node, lambda: tracks and len(tracks[-1].poses) == 4, 10)
    assert rclpy.ok(context=ros_node.context)


def test_offline_csv_and_figure(tmp_path):
    from contact_correction.offline import main, read_csv
    from stereo_manip_tools.transforms import quaternion_from_matrix
    obs = noisy_insertion(8, seed=4)
    src = tmp_path / 'track.csv'
    with open(src, 'w') as fh:
        fh.write('# test\nstamp_ns,x,y,z,qx,qy,qz,qw\n')
        for k, T in enumerate(obs):
            fh.write(','.join(str(v) for v in [k * 10**7, *T[:3, 3],
                                               *quaternion_from_matrix(T[:3, :3])]) + '\n')
        fh.write(f'{8 * 10**7},nan,0,0,0,0,0,1\n')        # bad row: passed through
    out, fig = tmp_path / 'out.csv', tmp_path / 'fig9.png'
    assert main([str(src), '-o', str(out), '--figure', str(fig), '--tolerance', '0.004']) == 0
    assert fig.is_file() and fig.stat().st_size > 10000
    stamps, Tm, _ = read_csv(out)
    lines = [ln for ln in out.read_text().splitlines() if not ln.startswith('#')]
    assert lines[0].startswith('stamp_ns,x,y,z,qx,qy,qz,qw,corrected,method')
    assert [ln.split(',')[8] for ln in lines[1:]] == ['1'] * 8 + ['0']
    assert np.allclose(Tm[:8, :2, 3], 0.0, atol=1e-8)
    assert np.allclose(Tm[:8, 2, 3], obs[:, 2, 3], atol=1e-8)
    # a CSV without the required columns is a clear error, exit code 2
    bad = tmp_path / 'bad.csv'
    bad.write_text('t,x,y\n1,2,3\n')
    assert main([str(bad), '-o', str(tmp_path / 'x.csv')]) == 2


def test_offline_bag(tmp_path):
    from rclpy.serialization import serialize_message
    from contact_correction.offline import main, read_csv
    from stereo_manip_tools.bag_io import BagWriter
    obs = noisy_insertion(5, seed=5)
    bag = tmp_path / 'bag'
    with BagWriter(bag) as w:
        w.add_topic('/peg_pose', 'geometry_msgs/msg/PoseStamped')
        w.add_topic('/block_pose', 'geometry_msgs/msg/PoseStamped')
        w.write('/block_pose', 1, serialize_message(_stamped(np.eye(4), 1)))
        for k, T in enumerate(obs):
            w.write('/peg_pose', (k + 2) * 10**7, serialize_message(_stamped(T, (k + 2) * 10**7)))
    out = tmp_path / 'out.csv'
    assert main([str(bag), '-o', str(out), '--moving-topic', '/peg_pose', '--fixed-topic',
                 '/block_pose', '--tolerance', '0.004']) == 0
    stamps, Tm, _ = read_csv(out)
    assert len(stamps) == 5 and np.allclose(Tm[:, :2, 3], 0.0, atol=1e-8)
