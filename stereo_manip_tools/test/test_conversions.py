"""Round trips between ROS messages and arrays (no graph needed)."""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from stereo_manip_tools.conversions import (
    camera_info_from_parameters, CameraInfoError, image_to_numpy, IMAGE_ENCODINGS,
    matrices_to_path, matrix_to_pose, ns_to_stamp, numpy_to_image, path_to_matrices,
    pointcloud2_to_array, pose_to_matrix, stamp_to_ns, StereoCameraParameters,
    stereo_parameters_from_camera_info, xyz_to_pointcloud2)
from stereo_manip_tools.transforms import make_transform, rotation_about_axis


@pytest.mark.parametrize('encoding', sorted(IMAGE_ENCODINGS))
def test_image_round_trip(encoding):
    dtype, ch = IMAGE_ENCODINGS[encoding]
    rng = np.random.default_rng(3)
    shape = (5, 7) if ch == 1 else (5, 7, ch)
    arr = (rng.random(shape) * 200).astype(dtype)
    msg = numpy_to_image(arr, encoding, Header(frame_id='cam'))
    assert msg.header.frame_id == 'cam' and msg.encoding == encoding
    out = image_to_numpy(msg)
    assert out.dtype == arr.dtype and np.array_equal(out, arr)


def test_image_with_row_padding_and_big_endian():
    arr = np.arange(12, dtype=np.uint16).reshape(3, 4)
    msg = Image(height=3, width=4, encoding='mono16', is_bigendian=1, step=10)
    padded = np.zeros((3, 10), dtype=np.uint8)
    padded[:, :8] = arr.astype('>u2').view(np.uint8).reshape(3, 8)
    msg.data = padded.tobytes()
    assert np.array_equal(image_to_numpy(msg), arr)


def test_image_errors_are_named():
    with pytest.raises(ValueError, match='unsupported image encoding'):
        image_to_numpy(Image(height=1, width=1, encoding='yuv422', step=2, data=b'\0\0'))
    with pytest.raises(ValueError, match='expected height'):
        image_to_numpy(Image(height=2, width=2, encoding='mono8', step=2, data=b'\0\0'))
    with pytest.raises(ValueError, match='channel'):
        numpy_to_image(np.zeros((2, 2), np.uint8), 'rgb8')
    with pytest.raises(ValueError, match='dtype'):
        numpy_to_image(np.zeros((2, 2), np.float64), 'mono8')


def test_pointcloud_round_trip_with_rgb_and_normals():
    rng = np.random.default_rng(4)
    P = rng.normal(size=(50, 3)).astype(np.float32)
    rgb = rng.integers(0, 256, size=(50, 3))
    N = rng.normal(size=(50, 3)).astype(np.float32)
    msg = xyz_to_pointcloud2(P, Header(frame_id='stereo_left_optical'), rgb=rgb, normals=N)
    out = pointcloud2_to_array(msg, ('x', 'y', 'z', 'rgb', 'normal_x', 'normal_y', 'normal_z'))
    assert out.shape == (50, 9)
    assert np.array_equal(out[:, :3], P.astype(float))
    assert np.array_equal(out[:, 3:6], rgb)
    assert np.array_equal(out[:, 6:], N.astype(float))


def test_pointcloud_skips_nan_and_reports_missing_field():
    P = np.array([[0, 0, 1], [np.nan, 0, 1], [1, 2, 3]], dtype=np.float32)
    msg = xyz_to_pointcloud2(P)
    assert not msg.is_dense
    assert pointcloud2_to_array(msg).shape == (2, 3)
    with pytest.raises(ValueError, match='no field'):
        pointcloud2_to_array(msg, ('x', 'intensity'))


@settings(max_examples=50, deadline=None)
@given(st.integers(0, 2**62))
def test_stamp_round_trip(ns):
    assert stamp_to_ns(ns_to_stamp(ns)) == ns


def test_pose_and_path_round_trip():
    Ts = np.array([make_transform(rotation_about_axis([1, 1, 0], 0.3 * k), [k, -k, 0.5])
                   for k in range(5)])
    for T in Ts:
        assert np.allclose(pose_to_matrix(matrix_to_pose(T)), T, atol=1e-12)
    path = matrices_to_path(Ts, 'stereo_left_optical', [10, 20, 30, 40, 50])
    back, stamps = path_to_matrices(path)
    assert np.allclose(back, Ts, atol=1e-12) and stamps.tolist() == [10, 20, 30, 40, 50]
    assert path.poses[2].header.frame_id == 'stereo_left_optical'


def test_camera_info_round_trip_reproduces_baseline():
    params = StereoCameraParameters(fx=500.0, fy=500.0, cx=320.0, cy=240.0, baseline=0.12,
                                    width=640, height=480)
    left, right = camera_info_from_parameters(params, Header(frame_id='stereo_left_optical'))
    assert right.p[3] == pytest.approx(-500.0 * 0.12)
    assert stereo_parameters_from_camera_info(left, right) == params
    z = params.depth_from_disparity(np.array([[60.0, 0.0]]))
    assert z[0, 0] == pytest.approx(1.0) and np.isnan(z[0, 1])


def test_camera_info_errors_name_their_reason():
    with pytest.raises(CameraInfoError, match='focal length') as exc:
        stereo_parameters_from_camera_info(CameraInfo(), CameraInfo())
    assert exc.value.reason == 'bad_camera_info' and isinstance(exc.value, ValueError)
    params = StereoCameraParameters(500.0, 500.0, 320.0, 240.0, 0.1, 640, 480)
    left, right = camera_info_from_parameters(params, Header())
    right.p[3] = 0.0
    with pytest.raises(CameraInfoError, match='baseline') as exc:
        stereo_parameters_from_camera_info(left, right)
    assert exc.value.reason == 'zero_baseline'
    left, right = camera_info_from_parameters(params, Header())
    right.p[0] = float('nan')
    with pytest.raises(CameraInfoError) as exc:
        stereo_parameters_from_camera_info(left, right)
    assert exc.value.reason == 'bad_camera_info'
    left, right = camera_info_from_parameters(params, Header())
    right.width = 320
    with pytest.raises(CameraInfoError, match='640x480') as exc:
        stereo_parameters_from_camera_info(left, right)
    assert exc.value.reason == 'size_mismatch'


def test_principal_point_offset_follows_middlebury():
    """Motorcycle (Middlebury 2014): f 994.978 px, doffs 31.086 px, baseline 193.001 mm;
    a disparity of 40 px is a depth of f * B / (d + doffs) = 2.70 m."""
    params = StereoCameraParameters(fx=994.978, fy=994.978, cx=311.193, cy=254.877,
                                    baseline=0.193001, width=741, height=500, doffs=31.086)
    left, right = camera_info_from_parameters(params, Header())
    assert right.p[2] - left.p[2] == pytest.approx(31.086)
    back = stereo_parameters_from_camera_info(left, right)
    assert back.doffs == pytest.approx(31.086)
    assert back.depth_from_disparity(np.array([[40.0]]))[0, 0] == pytest.approx(
        994.978 * 0.193001 / 71.086, rel=1e-6)


def test_input_qos_choices():
    from rclpy.qos import qos_profile_sensor_data, ReliabilityPolicy

    from stereo_manip_tools.parameters import input_qos_descriptor, input_qos_profile
    assert input_qos_profile('sensor_data') == qos_profile_sensor_data
    reliable = input_qos_profile('reliable', depth=5)
    assert reliable.reliability == ReliabilityPolicy.RELIABLE and reliable.depth == 5
    with pytest.raises(ValueError, match='input_qos must be one of'):
        input_qos_profile('fast')
    assert input_qos_descriptor('points2').read_only
