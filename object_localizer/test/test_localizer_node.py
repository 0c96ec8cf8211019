"""object_localizer_node as its own process: a cloud in, the object's pose out."""

from geometry_msgs.msg import PoseStamped
import numpy as np
from object_localizer.evaluation import add_s, sample_visible_surface
from object_localizer.localization import prepare_model
import pytest
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header
from stereo_manip_msgs.msg import TrackStatus
from stereo_manip_tools.conversions import ns_to_stamp, pointcloud2_to_array, pose_to_matrix, \
    xyz_to_pointcloud2
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.testing import spin_until, start_executable, wait_for_subscribers
from stereo_manip_tools.transforms import make_transform, rotation_about_axis


@pytest.mark.process
def test_node_publishes_pose_of_object_in_cloud(ros_node):
    arm = load_obj(find_model('link_arm'))
    T = make_transform(rotation_about_axis([0.2, 1.0, 0.1], 0.9), [0.03, -0.02, 0.7])
    points = sample_visible_surface(arm, T, 8000, seed=7)
    points += np.random.default_rng(7).normal(scale=0.0005, size=points.shape)
    header = Header(frame_id='stereo_left_optical', stamp=ns_to_stamp(1_234_000_000))
    cloud = xyz_to_pointcloud2(points, header)
    poses, clouds, statuses = [], [], []
    ros_node.create_subscription(PoseStamped, '/objects/link_arm/pose', poses.append, 10)
    ros_node.create_subscription(TrackStatus, '/objects/link_arm/status', statuses.append, 10)
    ros_node.create_subscription(PointCloud2, '/objects/link_arm/cloud', clouds.append, 10)
    bad = PointCloud2(header=header, height=1, width=10, point_step=12,
                      fields=[PointField(name='x', offset=0, datatype=7, count=1)],
                      data=b'\0' * 120)
    pub = ros_node.create_publisher(PointCloud2, '/points2', 10)
    with start_executable('object_localizer', 'object_localizer_node',
                          ros_args=['-p', 'models:=[link_arm]'], observer=ros_node,
                          wait_for_node='object_localizer') as proc:
        assert wait_for_subscribers(ros_node, [pub])
        pub.publish(bad)  # no y/z fields: rejected with a warning, node keeps going
        assert spin_until(ros_node, lambda: 'points2 rejected' in proc.output(), 20), \
            proc.output()
        pub.publish(cloud)
        assert spin_until(ros_node, lambda: len(poses) > 0 and len(clouds) > 0
                          and len(statuses) > 0, 30), proc.output()
        assert proc.running()
    assert statuses[0].header.stamp == header.stamp and statuses[0].object_name == 'link_arm'
    assert statuses[0].state == TrackStatus.TRACKING and statuses[0].quality > 0.5
    assert statuses[0].inlier_fraction > 0.8 and statuses[0].visible_residual < 0.0015
    got = poses[0]
    assert got.header.stamp == header.stamp and got.header.frame_id == 'stereo_left_optical'
    assert add_s(pose_to_matrix(got.pose), T, prepare_model(arm).points) < 0.0015
    # the segmented cloud is the object's points (all of them; nothing else was in the scene)
    assert abs(len(pointcloud2_to_array(clouds[0])) - len(points)) <= 0.01 * len(points)


@pytest.mark.process
def test_node_refuses_malformed_initial_poses():
    with start_executable('object_localizer', 'object_localizer_node',
                          ros_args=['-p', 'models:=[link_arm]',
                                    '-p', 'initial_poses:=[0.0, 0.0, 1.0]']) as proc:
        proc.process.wait(60)
        out = proc.output()
    assert proc.process.returncode != 0
    assert 'initial_poses has 3 numbers; expected 7 per model' in out
    assert 'Traceback' not in out


# --- the node in a live graph: restarts and start-up orders -----------------------------------

#: A bound that only catches hangs: issue #11's 5 s goal is a timing goal, measured (under the
#: exclusive CPU lock) by bench/localizer_restart.py, not by a timed test.
FIRST_POSE_S = 30.0


def _start_stream():
    """Start the producer (cloud_stream_peer.py) as its own process."""
    import subprocess
    import sys
    from pathlib import Path
    return subprocess.Popen([sys.executable, str(Path(__file__).with_name(
        'cloud_stream_peer.py'))], stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT)


def _first_verified_pose_after(node, poses, truths, t_start, timeout):
    """
    Time to the first pose after ``t_start`` and its ADD-S.

    Seconds from ``t_start`` (monotonic) to the first pose received after it, and the ADD-S
    of the first pose after it whose stamp's truth this node received (None if none within
    ``timeout``). The localizer can be sent a stream's first cloud before this node's truth
    subscription has matched the stream (measured once in a fresh clone's CI: the first
    pose's truth never arrived); the poses that follow it carry the error just as well.
    """
    import time
    n0 = len(poses)
    if not spin_until(node, lambda: len(poses) > n0, timeout):
        return None, None
    elapsed = time.monotonic() - t_start

    def scored():
        stamps = {(t.header.stamp.sec, t.header.stamp.nanosec): t for t in truths}
        for got in poses[n0:]:
            truth = stamps.get((got.header.stamp.sec, got.header.stamp.nanosec))
            if truth is not None:
                return got, truth
        return None
    if not spin_until(node, lambda: scored() is not None, 5.0):
        return elapsed, None
    got, truth = scored()
    peg = prepare_model(load_obj(find_model('peg')))
    return elapsed, add_s(pose_to_matrix(got.pose), pose_to_matrix(truth.pose), peg.points)


@pytest.mark.process
def test_producers_first_then_kill_9_and_restart_mid_stream(ros_node):
    """
    The stream runs before the localizer starts (no initial pose: global acquisition).

    The localizer is then killed with SIGKILL mid-stream and restarted: a verified pose within
    FIRST_POSE_S of each start, the producer never restarted, every pose within 5 mm of the truth.
    """
    import signal
    import time
    from stereo_manip_msgs.msg import TrackStatus
    poses, truths, statuses = [], [], []
    ros_node.create_subscription(PoseStamped, '/objects/peg/pose', poses.append, 10)
    ros_node.create_subscription(PoseStamped, '/objects/peg/pose_truth', truths.append, 50)
    ros_node.create_subscription(TrackStatus, '/objects/peg/status', statuses.append, 50)
    stream = _start_stream()
    try:
        assert spin_until(ros_node, lambda: len(truths) > 5, 60), 'producer did not stream'
        for attempt in range(2):
            t0 = time.monotonic()
            with start_executable('object_localizer', 'object_localizer_node',
                                  ros_args=['-p', 'models:=[peg]']) as proc:
                elapsed, err = _first_verified_pose_after(ros_node, poses, truths, t0, 30)
                assert elapsed is not None, proc.output()
                assert elapsed <= FIRST_POSE_S, f'first pose after {elapsed:.1f} s\n' \
                    + proc.output()
                assert err is not None and err < 0.005, err
                n = len(poses)
                spin_until(ros_node, lambda: len(poses) > n + 5, 10)
                if attempt == 0:
                    proc.process.send_signal(signal.SIGKILL)
                    proc.process.wait(10)
            assert stream.poll() is None, 'the producer was restarted or died'
        # every status names the object and a valid state; every received pose was verified
        assert statuses and all(s.object_name == 'peg' and s.state <= 3 for s in statuses)
    finally:
        stream.kill()
        stream.wait(10)


@pytest.mark.process
def test_consumers_first(ros_node):
    """
    Consumer and localizer up before any cloud exists.

    a verified pose within FIRST_POSE_S of the producer's first cloud.
    """
    import time
    poses, truths = [], []
    ros_node.create_subscription(PoseStamped, '/objects/peg/pose', poses.append, 10)
    ros_node.create_subscription(PoseStamped, '/objects/peg/pose_truth', truths.append, 50)
    with start_executable('object_localizer', 'object_localizer_node',
                          ros_args=['-p', 'models:=[peg]'], observer=ros_node,
                          wait_for_node='object_localizer') as proc:
        stream = _start_stream()
        try:
            assert spin_until(ros_node, lambda: len(truths) > 0, 60), 'producer did not stream'
            t0 = time.monotonic()
            elapsed, err = _first_verified_pose_after(ros_node, poses, truths, t0, 30)
            assert elapsed is not None, proc.output()
            assert elapsed <= FIRST_POSE_S, f'first pose after {elapsed:.1f} s\n' \
                + proc.output()
            assert err is not None and err < 0.005, err
            assert proc.running()
        finally:
            stream.kill()
            stream.wait(10)
