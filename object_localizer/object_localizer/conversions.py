"""
Messages <-> arrays for the object localizer.

Messages <-> arrays for the object localizer (the only module besides the node that knows
ROS message types).
"""

from __future__ import annotations

from typing import Optional

import numpy as np
from object_localizer.tracking import PoseQuality, TrackState
from sensor_msgs.msg import PointCloud2
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


def track_status(header: Header, name: str, state: TrackState, quality: PoseQuality | None,
                 reason: str) -> TrackStatus:
    """Make the ``TrackStatus`` of one object for one processed cloud."""
    msg = TrackStatus(header=header, object_name=name, state=int(state), reason=reason)
    if quality is not None:
        msg.quality = float(quality.quality)
        msg.inlier_fraction = float(quality.inlier_fraction)
        msg.visible_residual = float(quality.visible_residual) \
            if np.isfinite(quality.visible_residual) else float('nan')
        msg.prediction_error = float(quality.prediction_error)
    return msg
