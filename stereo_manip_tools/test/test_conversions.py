"""Round trips between ROS messages and arrays (no graph needed)."""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header
from stereo_manip_tools.conversions import (
    camera_info_from_parameters, CameraInfoError, DEFAULT_MAX_ABS_COORDINATE, IMAGE_ENCODINGS,
    image_to_numpy, matrices_to_path, matrix_to_pose, MAX_POINTS_RECEIVED, ns_to_stamp,
    numpy_to_image, path_to_matrices, pointcloud2_to_array, PointCloudError, pose_to_matrix,
    read_pointcloud2, stamp_to_ns, stereo_parameters_from_camera_info, StereoCameraParameters,
    xyz_to_pointcloud2)
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
    """
    Motorcycle (Middlebury 2014).

    f 994.978 px, doffs 31.086 px, baseline 193.001 mm; a disparity of 40 px is a depth of f * B /
    (d + doffs) = 2.70 m.
    """
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


# --- the hardened PointCloud2 reader ------------------------------------------------------

def _cloud(points, **overrides):
    msg = xyz_to_pointcloud2(np.asarray(points, dtype=np.float32), Header(frame_id='cam'))
    for k, v in overrides.items():
        setattr(msg, k, v)
    return msg


def _xyz_fields(names='xyz', offsets=(0, 4, 8), datatypes=(7, 7, 7)):
    """Make PointFields (datatype 7 = FLOAT32) with the given names, offsets and datatypes."""
    return [PointField(name=n, offset=o, datatype=d, count=1)
            for n, o, d in zip(names, offsets, datatypes)]


@pytest.mark.parametrize('change, reason', [
    ({'point_step': 0}, 'bad_layout'),
    ({'height': 2, 'width': 2, 'row_step': 4}, 'bad_layout'),
    ({'width': 10}, 'truncated'),
    ({'fields': _xyz_fields(offsets=(0, 4, 40))}, 'bad_field'),
    ({'fields': _xyz_fields(datatypes=(0, 7, 7))}, 'bad_datatype'),
    ({'fields': _xyz_fields(datatypes=(99, 7, 7))}, 'bad_datatype'),
    ({'fields': _xyz_fields(names='xxz')}, 'bad_field'),
    ({'fields': _xyz_fields(names='x', offsets=(0,), datatypes=(7,))}, 'missing_field'),
    ({'width': MAX_POINTS_RECEIVED + 1}, 'too_large'),
])
def test_pointcloud_layout_errors_name_their_reason(change, reason):
    msg = _cloud([[0.1, 0.2, 0.5], [0.3, 0.4, 0.6]], **change)
    with pytest.raises(PointCloudError) as info:
        read_pointcloud2(msg)
    assert info.value.reason == reason
    assert isinstance(info.value, ValueError)      # existing `except ValueError` still catch it


def test_pointcloud_big_endian_and_row_padding_are_honoured():
    P = np.array([[0.1, -0.2, 0.5], [0.3, 0.4, 0.6], [1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    rows = np.zeros((2, 40), dtype=np.uint8)          # 2 rows of 2 points, 16 bytes padding
    rows[:, :24] = P.astype('>f4').view(np.uint8).reshape(2, 24)
    msg = PointCloud2(height=2, width=2, point_step=12, row_step=40, is_bigendian=True,
                      fields=_xyz_fields(), data=rows.tobytes())
    assert np.allclose(read_pointcloud2(msg).points, P, atol=1e-6)


def test_pointcloud_word_aligned_layout_with_offset_padding_and_invalid_rows():
    """The strided float32 fast path: x at byte 4 of 16, padded rows, NaN/huge rows kept."""
    P = np.array([[0.1, -0.2, 0.5], [np.nan, 0.4, 0.6], [1.0, 2.0, 3.0], [4.0, 2e4, 6.0],
                  [0.7, 0.8, 0.9], [-1.0, -2.0, -3.0]], dtype=np.float32)
    rows = np.zeros((2, 56), dtype=np.uint8)           # 2 rows of 3 points, 8 bytes padding
    rec = np.zeros((6, 4), dtype='<f4')
    rec[:, 0] = 7.0                                      # an intensity before x, y, z
    rec[:, 1:] = P
    rows[:, :48] = rec.view(np.uint8).reshape(2, 48)
    msg = PointCloud2(height=2, width=3, point_step=16, row_step=56, is_bigendian=False,
                      fields=_xyz_fields(offsets=(4, 8, 12)), data=rows.tobytes())
    kept = read_pointcloud2(msg, keep_rows=True, dtype=np.float32)
    assert kept.points.dtype == np.float32 and kept.points.shape == (6, 3)
    assert (kept.nonfinite, kept.out_of_bounds) == (1, 1)
    good = [0, 2, 4, 5]
    assert np.array_equal(kept.points[good], P[good])
    assert np.all(np.isnan(kept.points[[1, 3]]))
    dropped = read_pointcloud2(msg)
    assert dropped.points.dtype == np.float64
    assert np.allclose(dropped.points, P[good].astype(np.float64))
    # every row valid: the same values, without NaN rows, in both modes
    clean = read_pointcloud2(_cloud(P[good]), keep_rows=True)
    assert np.allclose(clean.points, P[good]) and (clean.nonfinite, clean.out_of_bounds) == (0, 0)


def test_pointcloud_drops_nonfinite_and_huge_coordinates_with_counts():
    msg = _cloud([[0.1, 0.2, 0.5], [np.nan, 0, 1], [1e30, 0, 1], [0, np.inf, 1], [0, 0, -2e4]])
    reading = read_pointcloud2(msg)
    assert reading.points.shape == (1, 3) and reading.declared == 5
    assert (reading.nonfinite, reading.out_of_bounds) == (2, 2)


def test_pointcloud_cap_voxel_downsamples_a_surface():
    rng = np.random.default_rng(5)
    uv = rng.random((200_000, 2))
    P = np.c_[uv * 0.2, np.full(len(uv), 0.5)]        # a 20 cm square at z = 0.5 m
    reading = read_pointcloud2(_cloud(P), max_points=5000)
    assert 2500 <= len(reading.points) <= 5000 and reading.downsampled_from == 200_000
    assert reading.voxel_size > 0
    # centroids stay on the surface and cover it
    assert np.allclose(reading.points[:, 2], 0.5, atol=1e-6)
    assert reading.points[:, 0].min() < 0.01 and reading.points[:, 0].max() > 0.19


def test_pointcloud_cap_bounds_a_random_volume():
    P = np.random.default_rng(6).random((300_000, 3)) * 100.0
    reading = read_pointcloud2(_cloud(P), max_points=1000)
    assert len(reading.points) <= 1000 and np.all(np.isfinite(reading.points))


_FIELD = st.builds(lambda name, offset, datatype, count: PointField(
    name=name, offset=offset, datatype=datatype, count=count),
    st.sampled_from(['x', 'y', 'z', 'rgb', 'intensity']), st.integers(0, 40),
    st.integers(0, 10), st.integers(0, 3))


@settings(max_examples=300, deadline=None)
@given(width=st.integers(0, 40), height=st.integers(0, 4), point_step=st.integers(0, 48),
       row_step=st.integers(0, 400), fields=st.lists(_FIELD, max_size=6),
       big=st.booleans(), data=st.binary(max_size=2000),
       wanted=st.sampled_from([('x', 'y', 'z'), ('x', 'y', 'z', 'rgb'), ('intensity',)]))
def test_pointcloud_reader_never_fails_untyped(width, height, point_step, row_step, fields, big,
                                               data, wanted):
    """Any layout either reads (finite, bounded xyz) or raises PointCloudError."""
    msg = PointCloud2(width=width, height=height, point_step=point_step, row_step=row_step,
                      fields=fields, is_bigendian=big, data=data)
    try:
        reading = read_pointcloud2(msg, wanted, max_points=50)
    except PointCloudError as exc:
        assert exc.reason in ('bad_layout', 'truncated', 'bad_field', 'bad_datatype',
                              'missing_field', 'too_large')
        return
    assert len(reading.points) <= 50
    if wanted[:3] == ('x', 'y', 'z') and len(reading.points):
        assert np.all(np.abs(reading.points[:, :3]) <= DEFAULT_MAX_ABS_COORDINATE)
