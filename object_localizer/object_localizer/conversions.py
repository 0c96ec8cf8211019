"""
Messages <-> arrays for the object localizer.

Messages <-> arrays for the object localizer (the only module besides the node that knows
ROS message types).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from object_localizer.tracking import PoseQuality, TrackState
from object_localizer.verification import PinholeCamera
from sensor_msgs.msg import CameraInfo, PointCloud2
from std_msgs.msg import Header
from stereo_manip_msgs.msg import TrackStatus
from stereo_manip_tools.conversions import read_pointcloud2

__all__ = ['cloud_xyz', 'track_status']


def cloud_xyz(msg: PointCloud2, max_points: Optional[int] = None, voxel_size: float = 0.0
              ) -> np.ndarray:
    """
    x, y, z of a ``PointCloud2`` as an (N, 3) float32 array [m].

    Rows may be NaN (organised clouds keep them; :class:`object_localizer.tracking.SceneCloud`
    ignores them).

    Read by the shared hardened reader
    :func:`stereo_manip_tools.conversions.read_pointcloud2` (checked layout; NaN/inf and
    out-of-bounds coordinates become NaN rows; the usual float32 layout is one strided copy).
    With ``max_points`` a cloud with more valid points is voxel-downsampled to at most that
    many (bounded work per cloud).

    :raises stereo_manip_tools.conversions.PointCloudError: (a ValueError) unreadable layout.
    """
    return read_pointcloud2(msg, keep_rows=True, max_points=max_points, voxel_size=voxel_size,
                            dtype=np.float32).points


def camera_from_camera_info(msg: CameraInfo) -> PinholeCamera:
    """
    Return the rectified pinhole intrinsics (projection ``P``) of one camera's ``CameraInfo``.

    fx, fy, cx, cy [px] from ``P`` (the rectified image the cloud was computed from) and the
    image size [px].

    :raises ValueError: ``P`` not finite or its focal lengths not positive (P not set), or the
        image size is zero.
    """
    P = np.asarray(msg.p, dtype=float).reshape(3, 4)
    if not (np.all(np.isfinite(P)) and P[0, 0] > 0 and P[1, 1] > 0):
        raise ValueError(f'CameraInfo projection P has focal lengths fx={P[0, 0]}, '
                         f'fy={P[1, 1]} (P not set?)')
    if not (msg.width > 0 and msg.height > 0):
        raise ValueError(f'CameraInfo image size is {msg.width}x{msg.height}')
    return PinholeCamera(float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2]),
                         int(msg.width), int(msg.height))


def track_status(header: Header, name: str, state: TrackState, quality: PoseQuality | None,
                 reason: str, cpu_seconds: float = 0.0) -> TrackStatus:
    """Make the ``TrackStatus`` of one object for one processed cloud (CPU time in [s])."""
    msg = TrackStatus(header=header, object_name=name, state=int(state), reason=reason,
                      cpu_time=float(cpu_seconds))
    if quality is not None:
        msg.quality = float(quality.quality)
        msg.inlier_fraction = float(quality.inlier_fraction)
        msg.visible_residual = float(quality.visible_residual) \
            if np.isfinite(quality.visible_residual) else float('nan')
        msg.prediction_error = float(quality.prediction_error)
    return msg
