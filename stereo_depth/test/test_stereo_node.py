"""stereo_depth_node: in-process rclpy tests and executables started as separate processes."""

import time

import numpy as np
import pytest
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header
from stereo_depth.stereo_depth_node import (
    InputError, prepare_pair, stereo_geometry, StereoDepthNode)
from stereo_manip_tools.conversions import (camera_info_from_parameters, image_to_numpy,
                                            ns_to_stamp, numpy_to_image,
                                            pointcloud2_to_array, stamp_to_ns,
                                            StereoCameraParameters)
from stereo_manip_tools.testing import spin_until, start_executable
from stereo_msgs.msg import DisparityImage

FX, BASELINE, SHIFT = 100.0, 0.1, 6


def textured_pair(h=60, w=96, shift=SHIFT, seed=0):
    rng = np.random.default_rng(seed)
    tex = rng.integers(0, 256, (h, w + shift)).astype(np.uint8)
    return np.ascontiguousarray(tex[:, :w]), np.ascontiguousarray(tex[:, shift:])


def infos(w, h, stamp_ns, baseline=BASELINE):
    params = StereoCameraParameters(fx=FX, fy=FX, cx=(w - 1) / 2, cy=(h - 1) / 2,
                                    baseline=1.0, width=w, height=h)
    li, ri = camera_info_from_parameters(params, Header(stamp=ns_to_stamp(stamp_ns),
                                                        frame_id='left_optical'))
    p = list(ri.p)
    p[3] = -FX * baseline
    ri.p = p
    return li, ri


class Harness:
    """The node under test and a test node sharing one context and one executor."""

    def __init__(self, test_node, **overrides):
        params = [Parameter(k, value=v) for k, v in overrides.items()]
        self.node = StereoDepthNode(context=test_node.context, parameter_overrides=params)
        self.test = test_node
        self.executor = SingleThreadedExecutor(context=test_node.context)
        self.executor.add_node(self.node)
        self.executor.add_node(test_node)
        qos = qos_profile_sensor_data
        self.pub = {name: test_node.create_publisher(t, name, qos) for name, t in
                    (('left/image_rect', Image), ('right/image_rect', Image),
                     ('left/camera_info', CameraInfo), ('right/camera_info', CameraInfo))}
        self.got = {'disparity': [], 'depth': [], 'points2': []}
        for name, t in (('disparity', DisparityImage), ('depth', Image),
                        ('points2', PointCloud2)):
            test_node.create_subscription(t, name, self.got[name].append, 10)
        self.spin_until(lambda: all(p.get_subscription_count() > 0 for p in self.pub.values()),
                        5.0)

    def spin_until(self, predicate, timeout):
        deadline = time.monotonic() + timeout
        while not predicate() and time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.02)
        return predicate()

    def send(self, left, right, stamp_ns, right_stamp_ns=None, info=True, baseline=BASELINE,
             encoding='mono8', right_encoding=None):
        h, w = left.shape[:2]
        hl = Header(stamp=ns_to_stamp(stamp_ns), frame_id='left_optical')
        hr = Header(stamp=ns_to_stamp(right_stamp_ns if right_stamp_ns is not None
                                      else stamp_ns), frame_id='right_optical')
        if info:
            li, ri = infos(w, h, stamp_ns, baseline)
            self.pub['left/camera_info'].publish(li)
            self.pub['right/camera_info'].publish(ri)
            self.spin_until(lambda: False, 0.05)
        self.pub['left/image_rect'].publish(numpy_to_image(left, encoding, hl))
        self.pub['right/image_rect'].publish(numpy_to_image(right, right_encoding or encoding,
                                                            hr))

    def settle(self, predicate, timeout=10.0):
        return self.spin_until(predicate, timeout)

    def close(self):
        self.executor.remove_node(self.node)
        self.executor.remove_node(self.test)
        self.executor.shutdown()
        self.node.destroy_node()


@pytest.fixture
def harness(ros_node):
    made = []

    def make(**overrides):
        h = Harness(ros_node, **overrides)
        made.append(h)
        return h

    yield make
    for h in made:
        h.close()


# --- pure helpers -----------------------------------------------------------------------------

def test_prepare_pair_and_geometry_name_the_problem():
    left, right = textured_pair()
    lm = numpy_to_image(left, 'mono8')
    with pytest.raises(InputError, match='unsupported encoding') as exc:
        prepare_pair(numpy_to_image(left.astype(np.float32), '32FC1'), lm)
    assert exc.value.reason == 'unsupported_encoding'
    with pytest.raises(InputError, match='96x60 but right image is 95x60') as exc:
        prepare_pair(lm, numpy_to_image(right[:, :95].copy(), 'mono8'))
    assert exc.value.reason == 'size_mismatch'
    rgb = np.dstack([left, left // 2, left // 3])
    bgr = numpy_to_image(rgb[:, :, ::-1].copy(), 'bgr8')
    lo, ro, colours = prepare_pair(bgr, bgr)
    np.testing.assert_array_equal(colours, rgb)
    li, ri = infos(96, 60, 0)
    geo = stereo_geometry(li, ri, 96, 60)
    assert geo['baseline'] == pytest.approx(BASELINE) and geo['fx'] == FX
    with pytest.raises(InputError, match='right/camera_info') as exc:
        stereo_geometry(li, None, 96, 60)
    assert exc.value.reason == 'missing_camera_info'
    _, ri0 = infos(96, 60, 0, baseline=0.0)
    with pytest.raises(InputError, match='baseline') as exc:
        stereo_geometry(li, ri0, 96, 60)
    assert exc.value.reason == 'zero_baseline'
    with pytest.raises(InputError, match='CameraInfo is 96x60 but the images are 90x60'):
        stereo_geometry(li, ri, 90, 60)


# --- in-process node --------------------------------------------------------------------------

@pytest.mark.ros
def test_node_turns_a_pair_into_disparity_depth_and_points(harness):
    h = harness(max_disparity=16)
    left, right = textured_pair()
    h.send(left, right, 1_000_000_000)
    assert h.settle(lambda: all(h.got.values()))
    disp = image_to_numpy(h.got['disparity'][0].image)
    depth = image_to_numpy(h.got['depth'][0])
    inner = (slice(4, -4), slice(SHIFT + 4, -4))
    np.testing.assert_allclose(np.median(disp[inner]), SHIFT, atol=0.1)
    assert (np.abs(disp[inner] - SHIFT) <= 0.5).mean() > 0.97
    np.testing.assert_allclose(np.median(depth[inner]), FX * BASELINE / SHIFT, rtol=0.02)
    assert h.got['disparity'][0].t == pytest.approx(BASELINE)
    assert h.got['depth'][0].header.stamp.sec == 1
    pts = pointcloud2_to_array(h.got['points2'][0])
    assert len(pts) == np.isfinite(depth).sum()
    assert h.got['points2'][0].header.frame_id == 'left_optical'
    assert h.node.counters['processed'] == 1 and not h.node.rejected


@pytest.mark.ros
def test_decimated_organised_cloud_and_min_disparity(harness):
    h = harness(max_disparity=8, min_disparity=3, point_decimation=2, organized_cloud=True)
    left, right = textured_pair()
    h.send(left, right, 2_000_000_000)
    assert h.settle(lambda: all(h.got.values()))
    cloud = h.got['points2'][0]
    assert (cloud.height, cloud.width) == (30, 48) and not cloud.is_dense
    xyz = pointcloud2_to_array(cloud, skip_nans=False).reshape(30, 48, 3)
    depth = image_to_numpy(h.got['depth'][0])
    np.testing.assert_array_equal(np.isfinite(xyz[..., 2]), np.isfinite(depth[::2, ::2]))
    np.testing.assert_allclose(xyz[..., 2], depth[::2, ::2], equal_nan=True)
    disp_msg = h.got['disparity'][0]
    disp = image_to_numpy(disp_msg.image)
    assert disp_msg.min_disparity == 3.0 and disp_msg.max_disparity == 10.0
    assert np.all(disp[:, :3] < disp_msg.min_disparity)    # not searched: marked invalid
    assert (np.abs(disp[4:-4, SHIFT + 4:-4] - SHIFT) <= 0.5).mean() > 0.97


@pytest.mark.ros
def test_stereo_image_proc_names_are_aliases(harness):
    h = harness(disparity_range=24, P1=12.0, P2=200, correlation_window_size=7,
                uniqueness_ratio=15.0)
    p = h.node._params
    assert (p['max_disparity'], p['p1'], p['p2'], p['block_size']) == (24, 12, 200, 7)
    assert p['uniqueness'] == pytest.approx(0.15)
    node = h.node
    assert node.set_parameters([Parameter('stereo_algorithm', value=1)])[0].successful
    assert p['method'] == 'opencv_sgbm'
    res = node.set_parameters([Parameter('stereo_algorithm', value=5)])[0]
    assert not res.successful and 'stereo_algorithm' in res.reason
    res = node.set_parameters([Parameter('disparity_range', value=100000)])[0]
    assert not res.successful and p['max_disparity'] == 24
    assert node.describe_parameter('queue_size').read_only


@pytest.mark.ros
def test_unsubscribed_outputs_cost_nothing(ros_node):
    """No subscriber on any output: pairs are counted as skipped and not matched."""
    node = StereoDepthNode(context=ros_node.context,
                           parameter_overrides=[Parameter('max_disparity', value=16)])
    executor = SingleThreadedExecutor(context=ros_node.context)
    executor.add_node(node)
    executor.add_node(ros_node)
    try:
        pubs = {name: ros_node.create_publisher(t, name, qos_profile_sensor_data)
                for name, t in (('left/image_rect', Image), ('right/image_rect', Image),
                                ('left/camera_info', CameraInfo),
                                ('right/camera_info', CameraInfo))}
        left, right = textured_pair()
        deadline = time.monotonic() + 10.0
        k = 0
        while node.counters['skipped_unsubscribed'] < 2 and time.monotonic() < deadline:
            k += 1
            li, ri = infos(96, 60, k)
            hdr = Header(stamp=ns_to_stamp(k), frame_id='left_optical')
            pubs['left/camera_info'].publish(li)
            pubs['right/camera_info'].publish(ri)
            pubs['left/image_rect'].publish(numpy_to_image(left, 'mono8', hdr))
            pubs['right/image_rect'].publish(numpy_to_image(right, 'mono8', hdr))
            for _ in range(5):
                executor.spin_once(timeout_sec=0.02)
        assert node.counters['skipped_unsubscribed'] >= 2, node.counters
        assert node.counters['processed'] == 0
    finally:
        executor.remove_node(node)
        executor.remove_node(ros_node)
        executor.shutdown()
        node.destroy_node()


@pytest.mark.ros
def test_only_subscribed_outputs_are_built(ros_node, monkeypatch):
    """Only points2 subscribed (the live graph): no depth or disparity message is built."""
    import stereo_depth.stereo_depth_node as sdn
    built = {'image': 0, 'disparity': 0}
    real_image, real_disparity = sdn.numpy_to_image, sdn.StereoDepthNode._disparity_message

    def count_image(*a, **k):
        built['image'] += 1
        return real_image(*a, **k)

    def count_disparity(*a, **k):
        built['disparity'] += 1
        return real_disparity(*a, **k)

    monkeypatch.setattr(sdn, 'numpy_to_image', count_image)
    monkeypatch.setattr(sdn.StereoDepthNode, '_disparity_message', staticmethod(count_disparity))
    node = StereoDepthNode(context=ros_node.context, parameter_overrides=[
        Parameter('max_disparity', value=16), Parameter('point_decimation', value=2)])
    clouds = []
    ros_node.create_subscription(PointCloud2, 'points2', clouds.append, 10)
    executor = SingleThreadedExecutor(context=ros_node.context)
    executor.add_node(node)
    executor.add_node(ros_node)
    try:
        pubs = {name: ros_node.create_publisher(t, name, qos_profile_sensor_data)
                for name, t in (('left/image_rect', Image), ('right/image_rect', Image),
                                ('left/camera_info', CameraInfo),
                                ('right/camera_info', CameraInfo))}
        left, right = textured_pair()
        deadline = time.monotonic() + 10.0
        k = 0
        while len(clouds) < 2 and time.monotonic() < deadline:
            k += 1
            li, ri = infos(96, 60, k)
            hdr = Header(stamp=ns_to_stamp(k), frame_id='left_optical')
            pubs['left/camera_info'].publish(li)
            pubs['right/camera_info'].publish(ri)
            pubs['left/image_rect'].publish(numpy_to_image(left, 'mono8', hdr))
            pubs['right/image_rect'].publish(numpy_to_image(right, 'mono8', hdr))
            for _ in range(5):
                executor.spin_once(timeout_sec=0.02)
        assert len(clouds) >= 2, node.counters
        assert built == {'image': 0, 'disparity': 0}
        xyz = pointcloud2_to_array(clouds[-1])
        assert len(xyz) > 0.8 * 30 * 48                    # every 2nd pixel, most of them valid
        np.testing.assert_allclose(np.median(xyz[:, 2]), FX * BASELINE / SHIFT, rtol=0.02)
    finally:
        executor.remove_node(node)
        executor.remove_node(ros_node)
        executor.shutdown()
        node.destroy_node()


@pytest.mark.ros
def test_bad_input_is_rejected_counted_and_the_node_keeps_going(harness):
    h = harness(max_disparity=16)
    left, right = textured_pair()
    t = 1_000_000_000
    h.send(left, right[:, :90].copy(), t)                                  # mismatched sizes
    h.send(left.astype(np.float32), right.astype(np.float32), t + 1, encoding='32FC1')
    h.send(left, right, t + 2, baseline=0.0)                               # zero baseline
    expected = {'size_mismatch': 1, 'unsupported_encoding': 1, 'zero_baseline': 1}
    assert h.settle(lambda: h.node.rejected == expected), h.node.rejected
    h.send(left, right, t + 3)
    assert h.settle(lambda: len(h.got['disparity']) == 1)
    assert h.node.counters['processed'] == 1


@pytest.mark.ros
def test_missing_camera_info_is_rejected(harness):
    h = harness(max_disparity=16)
    left, right = textured_pair()
    h.send(left, right, 5_000, info=False)
    assert h.settle(lambda: h.node.rejected.get('missing_camera_info') == 1), h.node.rejected
    assert not h.got['disparity']


@pytest.mark.ros
def test_stamp_pairing_exact_and_approximate(harness):
    left, right = textured_pair()
    exact = harness(max_disparity=16)
    exact.send(left, right, 2_000_000_000, right_stamp_ns=2_003_000_000)   # 3 ms apart
    exact.settle(lambda: False, 1.0)
    assert exact.node.counters['received_pairs'] == 0 and not exact.got['disparity']
    exact.close()
    approx = harness(max_disparity=16, sync_tolerance=0.005)
    approx.send(left, right, 3_000_000_000, right_stamp_ns=3_003_000_000)
    assert approx.settle(lambda: len(approx.got['disparity']) == 1)
    assert approx.node.counters['received_pairs'] == 1


@pytest.mark.ros
def test_stale_frames_are_dropped_and_counted_not_queued(harness):
    h = harness(max_disparity=32, method='bp')          # ~0.1 s per frame: slow on purpose
    left, right = textured_pair(120, 160, seed=3)
    li, ri = infos(160, 120, 0)
    h.pub['left/camera_info'].publish(li)
    h.pub['right/camera_info'].publish(ri)
    assert h.settle(lambda: all(h.node._infos.values()), 5.0)
    # a burst: pairs arrive microseconds apart, far faster than one is processed
    for k in range(8):
        hdr = Header(stamp=ns_to_stamp(10_000_000_000 + k * 1_000_000), frame_id='left_optical')
        h.pub['left/image_rect'].publish(numpy_to_image(left, 'mono8', hdr))
        h.pub['right/image_rect'].publish(numpy_to_image(right, 'mono8', hdr))
    # Depth-1 subscriptions drop older samples in DDS already; what reaches the node and is
    # superseded before the worker takes it is dropped and counted. Either way the newest pair
    # is processed and the burst is not worked off one by one.
    c = h.node.counters
    newest = 10_000_000_000 + 7 * 1_000_000
    assert h.settle(lambda: any(stamp_to_ns(m.header.stamp) == newest
                                for m in h.got['disparity']), 30.0), c
    h.settle(lambda: False, 0.5)                         # nothing else arrives late
    assert c['processed'] + c['dropped_stale'] == c['received_pairs'], c
    assert 1 <= c['processed'] < 8, c
    assert len(h.got['disparity']) == c['processed']
    assert stamp_to_ns(h.got['disparity'][-1].header.stamp) == newest


@pytest.mark.ros
def test_pairs_beyond_max_rate_are_skipped_at_the_input_and_counted(harness):
    """A 30 Hz camera under max_rate 10: every third pair is processed, the rest counted."""
    h = harness(max_disparity=16, max_rate=10.0)
    left, right = textured_pair(60, 96, seed=5)
    for k in range(9):
        h.send(left, right, 1_000_000_000 + k * 33_333_333)
        assert h.settle(lambda: h.node.counters['received_pairs'] == k + 1, 5.0)
        h.settle(lambda: h.node.counters['processed'] + h.node.counters['skipped_rate']
                 + h.node.counters['dropped_stale'] >= k + 1, 5.0)
    c = h.node.counters
    assert c['skipped_rate'] == 6 and c['processed'] == 3 and c['dropped_stale'] == 0, c
    assert [stamp_to_ns(m.header.stamp) for m in h.got['disparity']] == \
        [1_000_000_000 + k * 33_333_333 for k in (0, 3, 6)]
    # changed at run time: 0 lets every pair through
    h.node.set_parameters([Parameter('max_rate', value=0.0)])
    h.send(left, right, 2_000_000_000)
    assert h.settle(lambda: c['processed'] == 4, 5.0), c


@pytest.mark.ros
def test_parameters_are_validated_and_changeable_at_run_time(harness):
    h = harness(max_disparity=16)
    node = h.node
    assert not node.set_parameters([Parameter('method', value='magic')])[0].successful
    assert not node.set_parameters([Parameter('median', value=4)])[0].successful
    assert not node.set_parameters([Parameter('p1', value=500)])[0].successful   # > p2
    res = node.set_parameters([Parameter('max_disparity', value=100000)])[0]
    assert not res.successful
    assert node.get_parameter('method').value == 'block_matching'
    assert node.set_parameters([Parameter('method', value='opencv_sgbm')])[0].successful
    left, right = textured_pair(64, 128, seed=5)
    h.send(left, right, 7_000)
    assert h.settle(lambda: len(h.got['disparity']) == 1)
    disp = image_to_numpy(h.got['disparity'][0].image)
    # OpenCV SGBM leaves the first num_disparities columns empty (-1): the method was switched
    assert np.all(disp[:, :10] == -1.0)
    assert (np.abs(disp[8:-8, 24:-8] - SHIFT) <= 0.5).mean() > 0.9
    desc = node.describe_parameter('max_disparity')
    assert desc.integer_range[0].from_value == 2 and desc.description
    assert node.describe_parameter('sync_queue_size').read_only


# --- separate processes -----------------------------------------------------------------------

@pytest.mark.process
def test_node_process_reports_bad_input_and_keeps_running(ros_node):
    with start_executable('stereo_depth', 'stereo_depth_node',
                          ros_args=['-p', 'max_disparity:=16'], observer=ros_node,
                          wait_for_node='stereo_depth_node') as proc:
        qos = qos_profile_sensor_data
        pubs = {n: ros_node.create_publisher(t, n, qos) for n, t in
                (('left/image_rect', Image), ('right/image_rect', Image),
                 ('left/camera_info', CameraInfo), ('right/camera_info', CameraInfo))}
        spin_until(ros_node, lambda: all(p.get_subscription_count() for p in pubs.values()), 10)
        left, right = textured_pair()
        got = []
        ros_node.create_subscription(DisparityImage, 'disparity', got.append, 10)

        def send(stamp, baseline):
            li, ri = infos(96, 60, stamp, baseline)
            pubs['left/camera_info'].publish(li)
            pubs['right/camera_info'].publish(ri)
            spin_until(ros_node, lambda: False, 0.2)
            hdr = Header(stamp=ns_to_stamp(stamp), frame_id='left_optical')
            pubs['left/image_rect'].publish(numpy_to_image(left, 'mono8', hdr))
            pubs['right/image_rect'].publish(numpy_to_image(right, 'mono8', hdr))

        # sensor-data QoS is best effort: resend until the node has seen the frame
        stamp = 1_000_000_000
        for _ in range(10):
            stamp += 1_000_000
            send(stamp, 0.0)
            if proc.wait_for_output('zero_baseline', 2.0):
                break
        assert 'zero_baseline' in proc.output()
        for _ in range(10):
            stamp += 1_000_000
            send(stamp, BASELINE)
            if spin_until(ros_node, lambda: len(got) >= 1, 2.0):
                break
        assert got, proc.output()
        assert proc.running
        out = proc.output()
        assert 'baseline from right CameraInfo' in out and 'must be > 0' in out


@pytest.mark.process
def test_camera_and_stereo_nodes_give_points_within_one_percent(ros_node):
    camera_args = ['-p', 'rate:=2.0', '-p', 'start_frame:=60', '-p', 'publish_disparity:=true']
    with start_executable('stereo_depth', 'synthetic_camera', ros_args=camera_args,
                          observer=ros_node, wait_for_node='synthetic_camera',
                          timeout=60.0) as cam, \
            start_executable('stereo_depth', 'stereo_depth_node',
                             ros_args=['-p', 'max_disparity:=128'], observer=ros_node,
                             wait_for_node='stereo_depth_node', timeout=60.0) as stereo:
        clouds, depths, occl, info = {}, {}, {}, []

        def key(msg):
            return (msg.header.stamp.sec, msg.header.stamp.nanosec)

        ros_node.create_subscription(PointCloud2, 'points2',
                                     lambda m: clouds.__setitem__(key(m), m), 10)
        ros_node.create_subscription(Image, 'depth_truth',
                                     lambda m: depths.__setitem__(key(m), m), 10)
        ros_node.create_subscription(Image, 'occlusion_truth',
                                     lambda m: occl.__setitem__(key(m), m), 10)
        ros_node.create_subscription(CameraInfo, 'left/camera_info', info.append,
                                     qos_profile_sensor_data)

        def matched():
            return [k for k in clouds if k in depths and k in occl]

        ok = spin_until(ros_node, lambda: len(matched()) >= 2 and info, 90.0)
        assert ok, f'no matching frames; camera:\n{cam.output()}\nstereo:\n{stereo.output()}'
        K = np.asarray(info[0].k).reshape(3, 3)
        for k in matched()[:2]:
            pts = pointcloud2_to_array(clouds[k])
            z_true = image_to_numpy(depths[k])
            occluded = image_to_numpy(occl[k]) > 0
            h, w = z_true.shape
            u = np.rint(K[0, 0] * pts[:, 0] / pts[:, 2] + K[0, 2]).astype(int)
            v = np.rint(K[1, 1] * pts[:, 1] / pts[:, 2] + K[1, 2]).astype(int)
            inside = (u >= 0) & (u < w) & (v >= 0) & (v < h)
            good = np.zeros((h, w), bool)
            uu, vv, zz = u[inside], v[inside], pts[inside, 2]
            zt = z_true[vv, uu]
            good[vv, uu] = np.abs(zz - zt) <= 0.01 * zt
            target = np.isfinite(z_true) & ~occluded      # surfaces are all textured
            frac = good[target].mean()
            assert frac >= 0.95, f'frame {k}: only {frac:.3f} of visible pixels within 1 %'
