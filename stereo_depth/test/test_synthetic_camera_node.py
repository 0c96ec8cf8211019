"""
synthetic_camera node.

parameters, synchronized publishing, CameraInfo geometry (in-process and as its own process from
the install tree).
"""


import math

from geometry_msgs.msg import PoseStamped
import numpy as np
import pytest
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image
from stereo_depth.synthetic_camera_node import SyntheticCameraNode, validate_parameter
from stereo_manip_tools.conversions import image_to_numpy, stereo_parameters_from_camera_info
from stereo_manip_tools.testing import spin_until, start_executable
from stereo_msgs.msg import DisparityImage

SMALL = [Parameter('width', value=160), Parameter('height', value=120),
         Parameter('fx', value=150.0), Parameter('rate', value=20.0)]


def test_validate_parameter_reasons():
    assert 'fx' in validate_parameter('fx', 0.0, {})
    assert 'unknown scene' in validate_parameter('scene', 'kitchen', {})
    assert 'rate' in validate_parameter('rate', -5.0, {})
    assert 'baseline' in validate_parameter('baseline', 0.0, {})
    assert 'encoding' in validate_parameter('encoding', 'bgr16', {})
    assert validate_parameter('left_file', '', {'source': 'files'}) is not None
    assert validate_parameter('scene', 'primitives', {}) is None
    assert validate_parameter('fx', 500.0, {}) is None


class _Collector:
    def __init__(self, node, topics):
        self.msgs = {t: [] for t in topics}
        self.subs = [node.create_subscription(mt, t, self.msgs[t].append, 10)
                     for t, mt in topics.items()]


def _spin_both(cam, obs, pred, timeout):
    return spin_until([obs, cam], pred, timeout)


@pytest.mark.ros
def test_node_refuses_bad_parameters_on_set_and_keeps_running(ros_node):
    cam = SyntheticCameraNode(context=ros_node.context, parameter_overrides=SMALL)
    try:
        for name, value, word in (('fx', 0.0, 'fx'), ('rate', -1.0, 'rate'),
                                  ('scene', 'nope', 'unknown scene'),
                                  ('baseline', 0.0, 'baseline')):
            res = cam.set_parameters([Parameter(name, value=value)])[0]
            assert not res.successful and word in res.reason, (name, res.reason)
        assert cam.get_parameter('fx').value == 150.0
        assert cam.set_parameters([Parameter('scene', value='primitives')])[0].successful
        c = _Collector(ros_node, {'objects/torus/pose_truth': PoseStamped,
                                  'left/image_rect': Image})
        assert _spin_both(cam, ros_node, lambda: len(c.msgs['objects/torus/pose_truth']) >= 1
                          and len(c.msgs['left/image_rect']) >= 1, 30)
        img = c.msgs['left/image_rect'][-1]
        assert (img.width, img.height, img.encoding) == (160, 120, 'mono8')
    finally:
        cam.destroy_node()


@pytest.mark.ros
def test_node_publishes_synchronized_pair_and_truth_in_process(ros_node):
    cam = SyntheticCameraNode(context=ros_node.context, parameter_overrides=SMALL + [
        Parameter('scene', value='revolute_pair'), Parameter('encoding', value='rgb8')])
    topics = {'left/image_rect': Image, 'right/image_rect': Image,
              'left/camera_info': CameraInfo, 'right/camera_info': CameraInfo,
              'objects/link_arm/pose_truth': PoseStamped, 'depth_truth': Image,
              'disparity_truth': DisparityImage, 'occlusion_truth': Image}
    try:
        c = _Collector(ros_node, topics)
        assert _spin_both(cam, ros_node, lambda: all(len(v) >= 3 for v in c.msgs.values()), 40)
    finally:
        cam.destroy_node()
    m = c.msgs
    stamps = [[(x.header.stamp.sec, x.header.stamp.nanosec) for x in m[t][:3]] for t in topics]
    assert all(s == stamps[0] for s in stamps), 'stamps differ between topics'
    assert len(set(stamps[0])) == 3
    left = image_to_numpy(m['left/image_rect'][0])
    assert left.shape == (120, 160, 3) and left.dtype == np.uint8
    params = stereo_parameters_from_camera_info(m['left/camera_info'][0],
                                                m['right/camera_info'][0])
    assert params.baseline == pytest.approx(0.10) and params.fx == 150.0
    assert m['left/camera_info'][0].header.frame_id == 'stereo_left_optical'
    assert m['right/camera_info'][0].header.frame_id == 'stereo_right_optical'
    depth = image_to_numpy(m['depth_truth'][0])
    disp = m['disparity_truth'][0]
    d = image_to_numpy(disp.image)
    ok = np.isfinite(depth)
    np.testing.assert_allclose(d[ok], disp.f * disp.t / depth[ok], rtol=1e-6)
    assert np.all(d[~ok] < disp.min_disparity)


@pytest.mark.ros
def test_node_motorcycle_source(ros_node):
    cam = SyntheticCameraNode(context=ros_node.context, parameter_overrides=[
        Parameter('source', value='motorcycle'), Parameter('rate', value=10.0)])
    try:
        c = _Collector(ros_node, {'left/image_rect': Image, 'right/camera_info': CameraInfo,
                                  'left/camera_info': CameraInfo,
                                  'disparity_truth': DisparityImage})
        assert _spin_both(cam, ros_node, lambda: all(len(v) >= 1 for v in c.msgs.values()), 30)
    finally:
        cam.destroy_node()
    img = c.msgs['left/image_rect'][0]
    assert (img.width, img.height) == (741, 500)
    Pl = np.reshape(c.msgs['left/camera_info'][0].p, (3, 4))
    Pr = np.reshape(c.msgs['right/camera_info'][0].p, (3, 4))
    assert Pl[0, 0] == pytest.approx(994.978) and Pl[0, 2] == pytest.approx(311.193)
    assert Pr[0, 2] - Pl[0, 2] == pytest.approx(31.086)       # Middlebury doffs
    assert -Pr[0, 3] / Pr[0, 0] == pytest.approx(0.193001)
    d = image_to_numpy(c.msgs['disparity_truth'][0].image)
    assert np.mean(d >= 0) > 0.9 and np.nanmax(d) < 70


@pytest.mark.process
def test_executable_publishes_synchronized_pair(ros_node):
    topics = {'left/image_rect': Image, 'right/image_rect': Image,
              'left/camera_info': CameraInfo, 'right/camera_info': CameraInfo,
              'objects/peg/pose_truth': PoseStamped}
    c = _Collector(ros_node, topics)
    with start_executable('stereo_depth', 'synthetic_camera',
                          ros_args=['-p', 'rate:=15.0', '-p', 'baseline:=0.12'],
                          observer=ros_node, wait_for_node='synthetic_camera', timeout=60) as proc:
        ok = spin_until(ros_node, lambda: all(len(v) >= 5 for v in c.msgs.values()), 60)
        assert ok, proc.output()
        assert proc.running()
    m = c.msgs
    # Match by stamp: every left image has a right image and both infos with the same stamp.
    key = {t: {(x.header.stamp.sec, x.header.stamp.nanosec) for x in m[t]} for t in topics}
    common = set.intersection(*key.values())
    assert len(common) >= 3, 'no synchronized frames'
    left, right = m['left/image_rect'][0], m['right/image_rect'][0]
    assert (left.width, left.height, left.encoding) == (640, 480, 'mono8')
    assert (right.width, right.height) == (640, 480)
    Pr = np.reshape(m['right/camera_info'][0].p, (3, 4))
    assert -Pr[0, 3] / Pr[0, 0] == pytest.approx(0.12)
    assert m['objects/peg/pose_truth'][0].header.frame_id == 'stereo_left_optical'


@pytest.mark.process
def test_executable_refuses_bad_parameter_at_startup():
    for args, word in ((['-p', 'scene:=nope'], 'unknown scene'), (['-p', 'fx:=0.0'], 'fx'),
                       (['-p', 'rate:=-2.0'], 'rate')):
        with start_executable('stereo_depth', 'synthetic_camera', ros_args=args) as proc:
            try:
                code = proc.process.wait(60)
            except Exception:  # noqa: BLE001 - report the output on a hang
                pytest.fail(f'{args}: still running; output:\n{proc.output()}')
            out = proc.output()
        assert code == 2, out
        assert 'refused to start' in out and word in out, out


@pytest.mark.ros
def test_node_files_source_and_ground_truth_switch(ros_node, tmp_path):
    import cv2
    from stereo_depth.synthetic import render
    left, right, _ = render('primitives', 5, seed=1)
    cv2.imwrite(str(tmp_path / 'l.png'), left)
    cv2.imwrite(str(tmp_path / 'r.png'), right)
    cam = SyntheticCameraNode(context=ros_node.context, parameter_overrides=[
        Parameter('source', value='files'), Parameter('left_file', value=str(tmp_path / 'l.png')),
        Parameter('right_file', value=str(tmp_path / 'r.png')), Parameter('rate', value=20.0),
        Parameter('ground_truth', value=False)])
    try:
        c = _Collector(ros_node, {'left/image_rect': Image, 'right/camera_info': CameraInfo,
                                  'depth_truth': Image})
        assert _spin_both(cam, ros_node, lambda: len(c.msgs['left/image_rect']) >= 3, 30)
        assert c.msgs['depth_truth'] == []  # ground truth switched off
        np.testing.assert_array_equal(image_to_numpy(c.msgs['left/image_rect'][0]), left)
        Pr = np.reshape(c.msgs['right/camera_info'][0].p, (3, 4))
        assert -Pr[0, 3] / Pr[0, 0] == pytest.approx(0.10)
        # Switching to files without a path is refused with a reason.
        res = cam.set_parameters([Parameter('left_file', value='')])[0]
        assert not res.successful and 'left_file' in res.reason
    finally:
        cam.destroy_node()


def test_bounce_playback_is_continuous_and_loop_wraps():
    from stereo_depth.synthetic_camera_node import scene_frame, validate_parameter
    frames = [scene_frame(k, 5, 'bounce') for k in range(13)]
    assert frames == [0, 1, 2, 3, 4, 3, 2, 1, 0, 1, 2, 3, 4]
    assert all(abs(a - b) == 1 for a, b in zip(frames, frames[1:]))
    assert [scene_frame(k, 5, 'loop') for k in (0, 4, 5, 7)] == [0, 4, 5, 7]  # scene wraps
    assert scene_frame(9, 1, 'bounce') == 9
    assert 'playback' in validate_parameter('playback', 'reverse', {})


def _rcl_wake_ups(clock, period, seconds, wake):
    """
    Call ``wake()`` as the rcl timer does, on a simulated clock.

    Call ``wake()`` as the rcl timer does (a period missed by more than a period is skipped)
    on a simulated clock ``clock['t']`` that ``wake`` advances by its rendering cost.
    """
    t_end = clock['t'] + seconds
    next_call = clock['t']
    while clock['t'] < t_end:
        clock['t'] = max(clock['t'], next_call)
        now = clock['t']
        next_call += period                     # rcl_timer_call: keep the phase, skip misses
        if next_call < now:
            next_call += math.ceil((now - next_call) / period) * period
        wake()


def _grid_frames(catch_up, costs, seconds):
    """Frames a 10 Hz FrameGrid renders in ``seconds`` when frame i costs ``costs(i)`` s."""
    from stereo_depth.synthetic_camera_node import FrameGrid
    grid, clock, n = FrameGrid(10.0, catch_up), {'t': 1000.0}, [0]

    def wake():
        for _ in range(grid.due(clock['t'])[0]):
            clock['t'] += costs(n[0])
            n[0] += 1
    _rcl_wake_ups(clock, 0.1, seconds, wake)
    return n[0]


def test_frame_grid_holds_the_rate_when_wake_ups_come_late():
    from stereo_depth.synthetic_camera_node import FrameGrid
    # every 4th frame takes 2.6 periods (a loaded machine), the others 0.2: 0.8 periods on
    # average, so a camera with a real clock keeps its 10 Hz
    costs = lambda i: 0.26 if i % 4 == 3 else 0.02        # noqa: E731
    assert _grid_frames(3, costs, 60.0) == pytest.approx(600, abs=3)
    # without catch-up the skipped periods are lost: the plain rcl timer's behaviour
    assert _grid_frames(0, costs, 60.0) < 0.9 * 600          # 480: 1 in 5 lost
    # on-time wake-ups: one frame each, exactly on the grid
    grid = FrameGrid(10.0, catch_up=3)
    assert [grid.due(5.0 + 0.1 * k + 0.003 * (k % 2)) for k in range(5)] == [(1, 0)] * 5
    # a wake-up 10 periods late: 3 missed frames rendered late, 6 dropped (counted)
    assert grid.due(5.0 + 0.1 * 4 + 1.0) == (4, 6)
    assert grid.next_index == 15
    # early (the timer's phase moved below the anchor): one frame, grid re-anchored
    assert grid.due(5.0 + 0.1 * 15 - 0.02) == (1, 0)
    assert grid.due(5.0 + 0.1 * 16 - 0.02) == (1, 0)
    with pytest.raises(ValueError, match='rate'):
        FrameGrid(0.0, 1)


@pytest.mark.ros
def test_free_running_node_publishes_every_period_or_counts_the_drop(ros_node):
    """
    The node on a simulated clock, wakes as the rcl timer gives them.

    When rendering now and then takes longer than the period the camera still publishes one frame
    per period, and when it falls too far behind the frames it could not render are counted, not
    lost.
    """
    cam = SyntheticCameraNode(context=ros_node.context, parameter_overrides=[
        p for p in SMALL if p.name != 'rate'] + [Parameter('rate', value=10.0)])
    try:
        cam._timer.cancel()                     # the test wakes the node itself
        c = _Collector(ros_node, {'objects/peg/pose_truth': PoseStamped})
        clock = {'t': 1000.0}
        cam._steady_clock = lambda: clock['t']
        render = cam._source.render
        n = {'k': 0}

        def slow_render(frame, **kwargs):
            n['k'] += 1
            clock['t'] += 0.26 if n['k'] % 4 == 0 else 0.02
            return render(frame, **kwargs)
        cam._source.render = slow_render
        _rcl_wake_ups(clock, 0.1, 20.0, cam._on_timer)
        published, dropped = cam.frames_published, cam.dropped_frames
        assert published == pytest.approx(200, abs=3), (published, dropped)
        assert cam.caught_up_frames > 20 and dropped == 0
        # far behind (1 s stalls): what cannot be caught up is dropped and counted
        cam.set_parameters([Parameter('catch_up_frames', value=1)])
        start_pub, start_next = cam.frames_published, cam._grid.next_index
        for _ in range(5):
            clock['t'] += 1.0
            cam._on_timer()
        new_pub, new_drop = cam.frames_published - start_pub, cam.dropped_frames - dropped
        assert new_pub == 10 and 40 <= new_drop <= 60, (new_pub, new_drop)   # 2 per wake-up
        assert new_pub + new_drop == cam._grid.next_index - start_next, \
            'every period is published or counted as dropped'
        spin_until([ros_node, cam], lambda: len(c.msgs['objects/peg/pose_truth']) >= 1, 10)
    finally:
        cam.destroy_node()
