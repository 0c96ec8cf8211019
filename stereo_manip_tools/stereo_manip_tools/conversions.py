"""
Conversions between ROS messages and numpy arrays, shared by every node (no rclpy needed).

Images (``sensor_msgs/Image``) <-> ``(H, W)`` or ``(H, W, C)`` arrays; point clouds
(``sensor_msgs/PointCloud2``) <-> ``(N, k)`` float arrays; poses (``geometry_msgs/Pose``,
``PoseStamped``, ``Transform``, ``nav_msgs/Path``) <-> 4x4 homogeneous matrices (metres);
stamps <-> integer nanoseconds; ``CameraInfo`` <-> the stereo parameters a matcher needs.
Every function validates its input and raises ``ValueError`` naming what is wrong.
"""

from __future__ import annotations

import array
from dataclasses import dataclass
import sys
from typing import Any, Iterable, Optional, Sequence, Tuple

from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion, Transform, \
    TransformStamped, Vector3
from nav_msgs.msg import Path
import numpy as np
from sensor_msgs.msg import CameraInfo, Image, PointCloud2, PointField
from std_msgs.msg import Header

from stereo_manip_tools.transforms import matrix_from_quaternion, quaternion_from_matrix

__all__ = [
    'IMAGE_ENCODINGS',
    'stamp_to_ns',
    'ns_to_stamp',
    'image_to_numpy',
    'numpy_to_image',
    'PointCloudError',
    'PointCloudReading',
    'MAX_POINTS_RECEIVED',
    'DEFAULT_MAX_ABS_COORDINATE',
    'read_pointcloud2',
    'pointcloud2_to_array',
    'xyz_to_pointcloud2',
    'float32_fields_to_pointcloud2',
    'pose_to_matrix',
    'matrix_to_pose',
    'transform_to_matrix',
    'matrix_to_transform',
    'pose_stamped_to_matrix',
    'matrix_to_pose_stamped',
    'pose_stamped_to_transform_stamped',
    'transform_stamped_to_matrix',
    'path_to_matrices',
    'matrices_to_path',
    'vector3_to_numpy',
    'numpy_to_vector3',
    'point_to_numpy',
    'numpy_to_point',
    'StereoCameraParameters',
    'CameraInfoError',
    'stereo_parameters_from_camera_info',
    'camera_info_from_parameters',
]

# encoding -> (numpy dtype, channels)
IMAGE_ENCODINGS = {
    'mono8': (np.uint8, 1), '8UC1': (np.uint8, 1),
    'mono16': (np.uint16, 1), '16UC1': (np.uint16, 1),
    'rgb8': (np.uint8, 3), 'bgr8': (np.uint8, 3), '8UC3': (np.uint8, 3),
    'rgba8': (np.uint8, 4), 'bgra8': (np.uint8, 4), '8UC4': (np.uint8, 4),
    '32FC1': (np.float32, 1), '32FC3': (np.float32, 3), '64FC1': (np.float64, 1),
    '16SC1': (np.int16, 1), '32SC1': (np.int32, 1),
}

_POINTFIELD_DTYPES = {
    PointField.INT8: np.int8, PointField.UINT8: np.uint8, PointField.INT16: np.int16,
    PointField.UINT16: np.uint16, PointField.INT32: np.int32, PointField.UINT32: np.uint32,
    PointField.FLOAT32: np.float32, PointField.FLOAT64: np.float64,
}


# --- stamps -------------------------------------------------------------------------------

def stamp_to_ns(stamp: Time) -> int:
    """``builtin_interfaces/Time`` to integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Time:
    """Integer nanoseconds to ``builtin_interfaces/Time``."""
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


# --- images -------------------------------------------------------------------------------

def _message_bytes(a: np.ndarray) -> array.array:
    """
    Copy the bytes of C-contiguous ``a`` into the ``array.array('B')`` of a ``uint8[]`` field.

    One copy and no per-byte Python work (the field's setter would copy ``bytes`` again, and
    iterate over anything else).
    """
    data = array.array('B')
    data.frombytes(a.reshape(-1).view(np.uint8))
    return data


def image_to_numpy(msg: Image) -> np.ndarray:
    """
    Decode a ``sensor_msgs/Image`` to an array of shape (H, W) or (H, W, C), copied.

    Row padding (``step``) and byte order are honoured; channel order is kept as encoded.

    :raises ValueError: unsupported encoding, or ``data`` too short for height x step.
    """
    if msg.encoding not in IMAGE_ENCODINGS:
        raise ValueError(f'unsupported image encoding {msg.encoding!r}; supported: '
                         + ', '.join(sorted(IMAGE_ENCODINGS)))
    dtype, channels = IMAGE_ENCODINGS[msg.encoding]
    dt = np.dtype(dtype).newbyteorder('>' if msg.is_bigendian else '<')
    row_bytes = msg.width * channels * dt.itemsize
    if msg.step < row_bytes:
        raise ValueError(f'image step {msg.step} < width*channels*itemsize = {row_bytes}')
    try:    # array.array (as rclpy delivers it), bytes, memoryview: a view, not a copy
        data = np.frombuffer(msg.data, dtype=np.uint8)
    except TypeError:       # a list of ints
        data = np.frombuffer(bytes(msg.data), dtype=np.uint8)
    if data.size < msg.height * msg.step:
        raise ValueError(f'image data has {data.size} bytes, expected height*step = '
                         f'{msg.height * msg.step}')
    rows = data[:msg.height * msg.step].reshape(msg.height, msg.step)[:, :row_bytes]
    arr = rows.view(dt).astype(dt.newbyteorder('='), copy=True)     # the one copy
    shape = (msg.height, msg.width) if channels == 1 else (msg.height, msg.width, channels)
    return arr.reshape(shape)


def numpy_to_image(array: np.ndarray, encoding: str, header: Optional[Header] = None) -> Image:
    """
    Encode an array of shape (H, W) or (H, W, C) as a ``sensor_msgs/Image``.

    :raises ValueError: encoding unknown or not matching the array's dtype/channels.
    """
    if encoding not in IMAGE_ENCODINGS:
        raise ValueError(f'unsupported image encoding {encoding!r}')
    dtype, channels = IMAGE_ENCODINGS[encoding]
    arr = np.asarray(array)
    got_channels = 1 if arr.ndim == 2 else (arr.shape[2] if arr.ndim == 3 else -1)
    if got_channels != channels:
        raise ValueError(f'encoding {encoding} needs {channels} channel(s), array shape is '
                         f'{arr.shape}')
    if arr.dtype != np.dtype(dtype):
        raise ValueError(f'encoding {encoding} needs dtype {np.dtype(dtype)}, got {arr.dtype}')
    arr = np.ascontiguousarray(arr)
    msg = Image()
    if header is not None:
        msg.header = header
    msg.height, msg.width = int(arr.shape[0]), int(arr.shape[1])
    msg.encoding = encoding
    msg.is_bigendian = int(sys.byteorder == 'big')
    msg.step = int(arr.shape[1] * channels * arr.dtype.itemsize)
    msg.data = _message_bytes(arr)     # one copy (tobytes + the field's setter: two)
    return msg


# --- point clouds -------------------------------------------------------------------------

class PointCloudError(ValueError):
    """
    A ``PointCloud2`` whose layout cannot be read safely.

    ``reason`` names the problem for counters: ``'bad_layout'`` (point_step 0, row_step too
    small, size overflow), ``'truncated'`` (data shorter than the layout declares),
    ``'bad_field'`` (a field that does not fit in point_step, a duplicate name, an rgb field
    that is not 4 bytes), ``'bad_datatype'`` (PointField datatype not 1-8), ``'missing_field'``
    or ``'too_large'`` (more points than :data:`MAX_POINTS_RECEIVED`).
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


#: Largest ``width * height`` a cloud may declare before it is refused (memory bound).
MAX_POINTS_RECEIVED = 20_000_000
#: Coordinates beyond this [m] are not a measurement (e.g. 1e30): such rows are dropped.
DEFAULT_MAX_ABS_COORDINATE = 1.0e4


@dataclass
class PointCloudReading:
    """
    What :func:`read_pointcloud2` read from one cloud, with the counts of what it dropped.

    :ivar points: shape (N, k) float64, the requested fields (rgb as three columns r, g, b).
    :ivar declared: points the message declared (``width * height``).
    :ivar nonfinite: rows dropped because x, y or z was NaN/inf.
    :ivar out_of_bounds: rows dropped because a coordinate exceeded ``max_abs_coordinate``.
    :ivar downsampled_from: rows before the point-count cap (0: no downsampling happened).
    :ivar voxel_size: voxel edge [m] of the downsampling (0: none).
    """

    points: np.ndarray
    declared: int
    nonfinite: int = 0
    out_of_bounds: int = 0
    downsampled_from: int = 0
    voxel_size: float = 0.0


def _cloud_bytes(msg: PointCloud2) -> np.ndarray:
    data = msg.data
    try:
        return np.frombuffer(data, dtype=np.uint8)
    except (TypeError, ValueError):
        return np.asarray(bytes(data), dtype=np.uint8) if not isinstance(data, list) else \
            np.asarray(data, dtype=np.uint8)


def _checked_layout(msg: PointCloud2, fields: Sequence[str]) -> Tuple[int, int, dict]:
    """(points declared, effective row step, {name: PointField}) after every layout check."""
    width, height, point_step = int(msg.width), int(msg.height), int(msg.point_step)
    n = width * height
    if n > MAX_POINTS_RECEIVED:
        raise PointCloudError('too_large', f'PointCloud2 declares {width}x{height} = {n} '
                                           f'points; at most {MAX_POINTS_RECEIVED} are read')
    if n and point_step <= 0:
        raise PointCloudError('bad_layout', f'PointCloud2 point_step is {point_step} for '
                                            f'{n} points')
    by_name: dict = {}
    for f in msg.fields:
        if f.name in by_name:
            raise PointCloudError('bad_field', f'PointCloud2 field {f.name!r} appears twice')
        by_name[f.name] = f
    for name in fields:
        if name not in by_name:
            raise PointCloudError('missing_field', f'PointCloud2 has no field {name!r}; '
                                  'fields: ' + (', '.join(by_name) or 'none'))
        f = by_name[name]
        if f.datatype not in _POINTFIELD_DTYPES:
            raise PointCloudError('bad_datatype', f'PointCloud2 field {name!r} has datatype '
                                  f'{f.datatype}; valid: 1-8 (INT8 .. FLOAT64)')
        size = np.dtype(_POINTFIELD_DTYPES[f.datatype]).itemsize * max(int(f.count), 1)
        if name in ('rgb', 'rgba') and size != 4:
            raise PointCloudError('bad_field', f'PointCloud2 field {name!r} is {size} bytes; '
                                  'packed colour needs 4')
        if n and f.offset + size > point_step:
            raise PointCloudError('bad_field', f'PointCloud2 field {name!r} (offset {f.offset},'
                                  f' {size} bytes) does not fit in point_step {point_step}')
    if n == 0:
        return 0, 0, by_name
    row_step = int(msg.row_step)
    if height == 1 and row_step < width * point_step:
        row_step = width * point_step        # a single row: row_step carries no information
    if row_step < width * point_step:
        raise PointCloudError('bad_layout', f'PointCloud2 row_step {row_step} < width * '
                                            f'point_step = {width * point_step}')
    needed = (height - 1) * row_step + width * point_step
    if len(msg.data) < needed:
        raise PointCloudError('truncated', f'PointCloud2 data has {len(msg.data)} bytes, '
                                           f'its layout needs {needed}')
    return n, row_step, by_name


def _voxel_downsample(points: np.ndarray, max_points: int, voxel_size: float
                      ) -> Tuple[np.ndarray, float]:
    """
    Down-sample a cloud to at most ``max_points`` voxel centroids.

    Centroids of occupied voxels of the first three columns, the voxel grown (as for a
    surface, by the square root of the excess) until at most ``max_points`` remain; a
    deterministic stride thins what a few growth steps leave above the cap.
    """
    xyz = points[:, :3]
    lo = xyz.min(axis=0)
    extent = float(np.max(xyz.max(axis=0) - lo))
    v = max(voxel_size, max(extent, 1e-9) / min(max_points, 2 ** 20))  # keys fit in int64
    out = points
    for _ in range(8):
        cells = np.floor((xyz - lo) / v).astype(np.int64)
        dims = cells.max(axis=0) + 1
        keys = cells[:, 0] + dims[0] * (cells[:, 1] + dims[1] * cells[:, 2])
        _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
        if len(counts) <= max_points:
            out = np.stack([np.bincount(inverse, weights=points[:, j], minlength=len(counts))
                            for j in range(points.shape[1])], axis=1) / counts[:, None]
            break
        v *= max(np.sqrt(len(counts) / max_points), 1.05)
    else:
        out = points
    if len(out) > max_points:
        out = out[np.linspace(0, len(out) - 1, max_points).astype(np.int64)]
    return out, float(v)


def read_pointcloud2(msg: PointCloud2, fields: Sequence[str] = ('x', 'y', 'z'), *,
                     drop_invalid: bool = True,
                     max_abs_coordinate: float = DEFAULT_MAX_ABS_COORDINATE,
                     max_points: Optional[int] = None,
                     voxel_size: float = 0.0, keep_rows: bool = False,
                     dtype: Any = np.float64) -> PointCloudReading:
    """
    Read a ``PointCloud2`` with the hardened reader every node uses.

    Checked layout, counted drops, bounded size.

    Checks ``point_step`` (> 0), ``row_step`` (honoured: organised clouds may pad rows), every
    requested field's datatype (1-8) and that it lies inside ``point_step``, duplicate names,
    and the data length; the byte order follows ``is_bigendian``. A field named ``rgb``/
    ``rgba`` (4 bytes) is unpacked to three columns r, g, b (0-255).

    With ``drop_invalid`` rows whose x, y or z is NaN/inf, or whose absolute value exceeds
    ``max_abs_coordinate`` [m], are dropped and counted. With ``max_points`` a larger cloud
    is voxel-downsampled (centroids, first three columns as coordinates, starting from
    ``voxel_size`` [m] when given) to at most that many rows, so the work per message stays
    bounded. With ``keep_rows`` (and no downsampling needed) invalid rows are set to NaN
    instead of dropped, so row indices stay those of the message (organised clouds).

    The usual layout (x, y, z consecutive native float32) is read as one strided view (about
    2 ms for 640x480); ``dtype`` is that of the returned points.

    :raises PointCloudError: the layout cannot be read (``reason`` names why).
    """
    n, row_step, by_name = _checked_layout(msg, fields)
    endian = '>' if msg.is_bigendian else '<'
    if n == 0:
        ncols = sum(3 if f in ('rgb', 'rgba') else 1 for f in fields)
        return PointCloudReading(np.zeros((0, ncols), dtype=dtype), 0)
    width, height, point_step = int(msg.width), int(msg.height), int(msg.point_step)
    raw = _cloud_bytes(msg)
    rows = np.lib.stride_tricks.as_strided(
        raw, shape=(height, width, point_step), strides=(row_step, point_step, 1),
        writeable=False).reshape(n, point_step)

    def column(name: str) -> np.ndarray:
        f = by_name[name]
        dt = np.dtype(_POINTFIELD_DTYPES[f.datatype]).newbyteorder(endian)
        return np.ascontiguousarray(rows[:, f.offset:f.offset + dt.itemsize]).view(dt)[:, 0]

    x0 = by_name['x'].offset if 'x' in by_name else -1
    native = '>' if sys.byteorder == 'big' else '<'
    fast = (tuple(fields) == ('x', 'y', 'z') and endian == native
            and all(by_name[k].datatype == PointField.FLOAT32
                    and by_name[k].offset == x0 + 4 * i for i, k in enumerate('xyz')))
    if fast and point_step % 4 == 0 and row_step % 4 == 0 and x0 % 4 == 0:
        # word-aligned layout: a strided float32 view of the buffer, one copy (the byte-wise
        # copy below costs ~30x more on 640x480)
        words = raw[:len(raw) - len(raw) % 4].view(np.float32)
        out = np.lib.stride_tricks.as_strided(
            words[x0 // 4:], shape=(height, width, 3), strides=(row_step, point_step, 4),
            writeable=False).reshape(n, 3).astype(dtype)
    elif fast:
        out = np.ascontiguousarray(rows[:, x0:x0 + 12]).view(np.float32).astype(dtype)
    else:
        cols = []
        for name in fields:
            if name in ('rgb', 'rgba'):
                f = by_name[name]
                packed = np.ascontiguousarray(rows[:, f.offset:f.offset + 4]).view(
                    np.dtype(np.uint32).newbyteorder(endian))[:, 0]
                cols.extend([(packed >> 16) & 255, (packed >> 8) & 255, packed & 255])
            else:
                cols.append(column(name))
        out = np.stack([np.asarray(c, dtype=dtype) for c in cols], axis=1) if cols else \
            np.zeros((n, 0), dtype=dtype)
    reading = PointCloudReading(out, n)
    if drop_invalid and all(k in by_name for k in 'xyz'):
        xyz = out[:, :3] if tuple(fields[:3]) == ('x', 'y', 'z') else np.stack(
            [np.asarray(column(k), dtype=np.float64) for k in 'xyz'], axis=1)
        with np.errstate(invalid='ignore'):
            all_valid = bool(np.abs(xyz).max() <= max_abs_coordinate)   # False if any NaN
            if all_valid:       # the usual case: one pass, no per-row masks, no copy below
                finite = valid = np.ones(len(xyz), dtype=bool)
            else:
                # the largest |coordinate| of each row: NaN if any is NaN, inf if any is inf
                # (one pass per column; np.all(..., axis=1) over (N, 3) costs ~8x more)
                a = np.abs(xyz)
                largest = np.maximum(np.maximum(a[:, 0], a[:, 1]), a[:, 2])
                finite = np.isfinite(largest)
                valid = largest <= max_abs_coordinate
        reading.nonfinite = int(len(finite) - np.count_nonzero(finite))
        reading.out_of_bounds = int(np.count_nonzero(finite) - np.count_nonzero(valid))
        needs_cap = max_points is not None and int(np.count_nonzero(valid)) > max_points
        if all_valid:
            reading.points = out
        elif keep_rows and not needs_cap:
            out = out.copy() if not out.flags.writeable else out
            out[~valid, :3] = np.nan
            reading.points = out
        else:
            reading.points = out[valid]
    if max_points is not None and len(reading.points) > max_points:
        if tuple(fields[:3]) != ('x', 'y', 'z'):
            raise ValueError('max_points needs x, y, z as the first three fields')
        pts = reading.points[np.all(np.isfinite(reading.points[:, :3]), axis=1)]
        reading.downsampled_from = len(pts)
        if len(pts) > max_points:
            pts, reading.voxel_size = _voxel_downsample(pts.astype(np.float64),
                                                        int(max_points), voxel_size)
        reading.points = pts.astype(dtype)
    return reading


def pointcloud2_to_array(msg: PointCloud2, fields: Sequence[str] = ('x', 'y', 'z'), *,
                         skip_nans: bool = True) -> np.ndarray:
    """
    Read the named fields of a ``PointCloud2`` into a float64 array of shape (N, len(fields)).

    :func:`read_pointcloud2` without the counts: same checks; with ``skip_nans`` rows with a
    non-finite or out-of-bounds x/y/z are dropped.

    :raises PointCloudError: (a ``ValueError``) the layout cannot be read or a field is absent.
    """
    return read_pointcloud2(msg, fields, drop_invalid=skip_nans).points


def xyz_to_pointcloud2(points: np.ndarray, header: Optional[Header] = None, *,
                       rgb: Optional[np.ndarray] = None,
                       normals: Optional[np.ndarray] = None) -> PointCloud2:
    """
    Build an unorganised ``PointCloud2`` (float32 x, y, z [m]; optional packed rgb, normals).

    :param points: shape (N, 3), metres, in ``header.frame_id``.
    :param rgb: shape (N, 3) uint8-range colours, packed into a float32 ``rgb`` field.
    :param normals: shape (N, 3) unit normals as ``normal_x/normal_y/normal_z``.
    """
    P = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(P)
    names = ['x', 'y', 'z']
    cols = [P[:, 0], P[:, 1], P[:, 2]]
    if rgb is not None:
        c = np.asarray(rgb).reshape(-1, 3).astype(np.uint32)
        if len(c) != n:
            raise ValueError(f'rgb has {len(c)} rows for {n} points')
        names.append('rgb')
        cols.append(((c[:, 0] << 16) | (c[:, 1] << 8) | c[:, 2]).view(np.float32))
    if normals is not None:
        nm = np.asarray(normals, dtype=np.float32).reshape(-1, 3)
        if len(nm) != n:
            raise ValueError(f'normals has {len(nm)} rows for {n} points')
        names += ['normal_x', 'normal_y', 'normal_z']
        cols += [nm[:, 0], nm[:, 1], nm[:, 2]]
    return float32_fields_to_pointcloud2(np.column_stack(cols).astype(np.float32, copy=False),
                                         names, header)


def float32_fields_to_pointcloud2(buffer: np.ndarray, fields: Sequence[str],
                                  header: Optional[Header] = None, *,
                                  is_dense: Optional[bool] = None) -> PointCloud2:
    """
    Wrap an array that already has the PointCloud2 layout: its bytes are copied once.

    :param buffer: (height, width, k) or (N, k) float32, C-contiguous: k float32 fields per
        point (a packed ``rgb`` keeps its uint32 bits in the float32). (N, k) gives an
        unorganised cloud (height 1); (height, width, k) an organised one.
    :param fields: the k field names, at offsets 0, 4, ..., 4 (k - 1).
    :param is_dense: no NaN point; None: computed from the first three fields.
    :raises ValueError: not float32, not contiguous, or k != len(fields).
    """
    b = np.asarray(buffer)
    if b.dtype != np.float32 or b.ndim not in (2, 3) or not b.flags.c_contiguous:
        raise ValueError(f'buffer must be a C-contiguous float32 (N, k) or (H, W, k) array, '
                         f'got {b.dtype} {b.shape}')
    k = b.shape[-1]
    if k != len(fields):
        raise ValueError(f'buffer has {k} fields per point, {len(fields)} names given')
    height, width = (1, b.shape[0]) if b.ndim == 2 else (b.shape[0], b.shape[1])
    msg = PointCloud2()
    if header is not None:
        msg.header = header
    msg.height, msg.width = int(height), int(width)
    msg.fields = [PointField(name=name, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, name in enumerate(fields)]
    msg.is_bigendian = sys.byteorder == 'big'
    msg.point_step = 4 * k
    msg.row_step = msg.point_step * msg.width
    if is_dense is None:
        is_dense = bool(np.isfinite(b.reshape(-1, k)[:, :3]).all())
    msg.is_dense = bool(is_dense)
    msg.data = _message_bytes(b)
    return msg


# --- poses --------------------------------------------------------------------------------

def vector3_to_numpy(v: Vector3) -> np.ndarray:
    """``Vector3`` to shape (3,)."""
    return np.array([v.x, v.y, v.z], dtype=float)


def numpy_to_vector3(a: Iterable[float]) -> Vector3:
    """Shape (3,) to ``Vector3``."""
    x, y, z = (float(c) for c in a)
    return Vector3(x=x, y=y, z=z)


def point_to_numpy(p: Point) -> np.ndarray:
    """``Point`` to shape (3,)."""
    return np.array([p.x, p.y, p.z], dtype=float)


def numpy_to_point(a: Iterable[float]) -> Point:
    """Shape (3,) to ``Point``."""
    x, y, z = (float(c) for c in a)
    return Point(x=x, y=y, z=z)


def _quat(q: Quaternion) -> np.ndarray:
    return np.array([q.x, q.y, q.z, q.w], dtype=float)


def pose_to_matrix(pose: Pose) -> np.ndarray:
    """
    ``geometry_msgs/Pose`` to a 4x4 transform (child -> parent).

    :raises ValueError: zero or non-finite quaternion, non-finite position, or a position
        beyond ``DEFAULT_MAX_ABS_COORDINATE`` (10 km: not a measurement, e.g. 1e30).
    """
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(_quat(pose.orientation))
    T[:3, 3] = point_to_numpy(pose.position)
    if not np.all(np.isfinite(T)):
        raise ValueError('pose has a non-finite position')
    if np.any(np.abs(T[:3, 3]) > DEFAULT_MAX_ABS_COORDINATE):
        raise ValueError(f'pose position {T[:3, 3]} m is beyond '
                         f'{DEFAULT_MAX_ABS_COORDINATE:g} m: not a measurement')
    return T


def matrix_to_pose(T: np.ndarray) -> Pose:
    """4x4 transform to ``geometry_msgs/Pose`` (quaternion with w >= 0)."""
    T = np.asarray(T, dtype=float)
    x, y, z, w = quaternion_from_matrix(T[:3, :3])
    return Pose(position=numpy_to_point(T[:3, 3]),
                orientation=Quaternion(x=float(x), y=float(y), z=float(z), w=float(w)))


def transform_to_matrix(tf: Transform) -> np.ndarray:
    """``geometry_msgs/Transform`` to a 4x4 transform."""
    T = np.eye(4)
    T[:3, :3] = matrix_from_quaternion(_quat(tf.rotation))
    T[:3, 3] = vector3_to_numpy(tf.translation)
    return T


def matrix_to_transform(T: np.ndarray) -> Transform:
    """4x4 transform to ``geometry_msgs/Transform``."""
    pose = matrix_to_pose(T)
    return Transform(translation=numpy_to_vector3(T[:3, 3]), rotation=pose.orientation)


def pose_stamped_to_matrix(msg: PoseStamped) -> Tuple[np.ndarray, int, str]:
    """``PoseStamped`` to ``(T 4x4, stamp_ns, frame_id)``."""
    return pose_to_matrix(msg.pose), stamp_to_ns(msg.header.stamp), msg.header.frame_id


def matrix_to_pose_stamped(T: np.ndarray, header: Header) -> PoseStamped:
    """4x4 transform and header to ``PoseStamped``."""
    return PoseStamped(header=header, pose=matrix_to_pose(T))


def pose_stamped_to_transform_stamped(msg: PoseStamped, child_frame: str) -> TransformStamped:
    """
    ``PoseStamped`` of a frame to the TF transform ``msg.header.frame_id -> child_frame``.

    The pose of ``child_frame`` in the header's frame is the transform that maps child
    coordinates into the parent (tf2 convention); stamp and parent frame are the header's. The
    quaternion is validated and normalised (``ValueError`` for NaN or zero).
    """
    if not child_frame:
        raise ValueError('empty child frame')
    T = pose_to_matrix(msg.pose)
    return TransformStamped(header=msg.header, child_frame_id=child_frame,
                            transform=matrix_to_transform(T))


def transform_stamped_to_matrix(msg: TransformStamped) -> Tuple[np.ndarray, int, str, str]:
    """
    ``TransformStamped`` to ``(T 4x4 child -> parent, stamp_ns, parent frame, child frame)``.

    :raises ValueError: zero or non-finite quaternion, non-finite translation.
    """
    T = transform_to_matrix(msg.transform)
    if not np.all(np.isfinite(T)):
        raise ValueError('transform has a non-finite translation')
    return T, stamp_to_ns(msg.header.stamp), msg.header.frame_id, msg.child_frame_id


def path_to_matrices(path: Path) -> Tuple[np.ndarray, np.ndarray]:
    """``nav_msgs/Path`` to ``(T (N, 4, 4), stamps_ns (N,) int64)``."""
    Ts = np.array([pose_to_matrix(p.pose) for p in path.poses]).reshape(-1, 4, 4)
    stamps = np.array([stamp_to_ns(p.header.stamp) for p in path.poses], dtype=np.int64)
    return Ts, stamps


def matrices_to_path(Ts: np.ndarray, frame_id: str, stamps_ns: Optional[Sequence[int]] = None
                     ) -> Path:
    """Convert transforms of shape (N, 4, 4) to a ``nav_msgs/Path``; stamps default 0..N-1 ns."""
    Ts = np.asarray(Ts, dtype=float).reshape(-1, 4, 4)
    stamps = list(stamps_ns) if stamps_ns is not None else list(range(len(Ts)))
    if len(stamps) != len(Ts):
        raise ValueError(f'{len(stamps)} stamps for {len(Ts)} poses')
    path = Path()
    path.header.frame_id = frame_id
    if len(Ts):
        path.header.stamp = ns_to_stamp(stamps[-1])
    path.poses = [matrix_to_pose_stamped(T, Header(stamp=ns_to_stamp(s), frame_id=frame_id))
                  for T, s in zip(Ts, stamps)]
    return path


# --- stereo camera info -------------------------------------------------------------------

@dataclass(frozen=True)
class StereoCameraParameters:
    """
    Rectified stereo geometry read from a left/right ``CameraInfo`` pair.

    :ivar fx, fy, cx, cy: left projection intrinsics [px].
    :ivar baseline: distance between the optical centres [m] (> 0).
    :ivar doffs: x-difference of the principal points, ``cx_right - cx_left`` [px], as
        Middlebury's ``doffs``: ``Z = fx * baseline / (d + doffs)`` with ``d = x_left -
        x_right``; 0 for the usual ROS rectification.
    :ivar width, height: image size [px].
    """

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    width: int
    height: int
    doffs: float = 0.0

    def depth_from_disparity(self, disparity: np.ndarray) -> np.ndarray:
        """Depth [m] ``fx * B / (d + doffs)``; NaN where the disparity is not positive/finite."""
        d = np.asarray(disparity, dtype=np.float64) + self.doffs
        with np.errstate(divide='ignore', invalid='ignore'):
            z = self.fx * self.baseline / d
        z[~(d > 0)] = np.nan
        return z.astype(np.float32)


class CameraInfoError(ValueError):
    """
    A rectified pair's ``CameraInfo`` that gives no usable stereo geometry.

    ``reason`` names the problem for counters: ``'bad_camera_info'`` (focal length not set or
    not finite), ``'zero_baseline'`` (baseline not positive) or ``'size_mismatch'``.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def stereo_parameters_from_camera_info(left: CameraInfo, right: CameraInfo
                                       ) -> StereoCameraParameters:
    """
    Stereo geometry from a rectified pair's ``CameraInfo`` (ROS convention P_r[3] = -fx*B).

    Depth is ``Z = fx B / (d + doffs)`` with ``doffs = cx_r - cx_l`` [px].

    :raises CameraInfoError: focal length not set, baseline not positive, or left and right
        sizes differ (``reason`` says which).
    """
    Pl = np.asarray(left.p, dtype=float).reshape(3, 4)
    Pr = np.asarray(right.p, dtype=float).reshape(3, 4)
    fx, fy = Pl[0, 0], Pl[1, 1]
    if not (np.isfinite(Pl).all() and np.isfinite(Pr).all() and fx > 0 and fy > 0
            and Pr[0, 0] > 0):
        raise CameraInfoError('bad_camera_info',
                              f'CameraInfo projection P has focal lengths fx={fx}, fy={fy}, '
                              f'right fx={Pr[0, 0]} (P not set?)')
    baseline = -Pr[0, 3] / Pr[0, 0]
    if not baseline > 0:
        raise CameraInfoError('zero_baseline',
                              f'baseline from right CameraInfo P[0,3]={Pr[0, 3]} is {baseline} '
                              'm; must be > 0 (ROS convention P[0,3] = -fx * baseline)')
    if (left.width, left.height) != (right.width, right.height):
        raise CameraInfoError('size_mismatch', f'left CameraInfo is {left.width}x{left.height}'
                                               f', right is {right.width}x{right.height}')
    return StereoCameraParameters(fx=float(fx), fy=float(fy), cx=float(Pl[0, 2]),
                                  cy=float(Pl[1, 2]), baseline=float(baseline),
                                  width=int(left.width), height=int(left.height),
                                  doffs=float(Pr[0, 2] - Pl[0, 2]))


def camera_info_from_parameters(params: StereoCameraParameters, header: Header
                                ) -> Tuple[CameraInfo, CameraInfo]:
    """Left and right ``CameraInfo`` of an ideal rectified pair (no distortion, R = I)."""
    infos = []
    for side in ('left', 'right'):
        ci = CameraInfo()
        ci.header = header
        ci.width, ci.height = params.width, params.height
        ci.distortion_model = 'plumb_bob'
        ci.d = [0.0] * 5
        cx = params.cx if side == 'left' else params.cx + params.doffs
        ci.k = [params.fx, 0.0, cx, 0.0, params.fy, params.cy, 0.0, 0.0, 1.0]
        ci.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        tx = 0.0 if side == 'left' else -params.fx * params.baseline
        ci.p = [params.fx, 0.0, cx, tx, 0.0, params.fy, params.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
        infos.append(ci)
    return infos[0], infos[1]
