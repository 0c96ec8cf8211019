"""Messages <-> arrays for the object localizer (the only module besides the node that knows
ROS message types)."""

from __future__ import annotations

import numpy as np
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from object_localizer.tracking import PoseQuality, TrackState
from stereo_manip_msgs.msg import TrackStatus
from stereo_manip_tools.conversions import pointcloud2_to_array

__all__ = ['cloud_xyz', 'track_status']


def cloud_xyz(msg: PointCloud2) -> np.ndarray:
    """x, y, z of a ``PointCloud2`` as an (N, 3) float32 array [m]; rows may be NaN (organised
    clouds keep them; :class:`object_localizer.tracking.SceneCloud` ignores them).

    Little-endian float32 x, y, z (the usual layout) are read as a strided view of the message
    buffer and copied once (about 1 ms for 640x480); any other layout goes through
    ``stereo_manip_tools.conversions.pointcloud2_to_array``.

    :raises ValueError: a field is missing or the data is shorter than declared.
    """
    by_name = {f.name: f for f in msg.fields}
    n = msg.width * msg.height
    fast = (not msg.is_bigendian and all(
        k in by_name and by_name[k].datatype == PointField.FLOAT32 and by_name[k].count == 1
        for k in 'xyz') and msg.point_step % 4 == 0
        and all(by_name[k].offset % 4 == 0 for k in 'xyz'))
    if not fast:
        return pointcloud2_to_array(msg, skip_nans=False).astype(np.float32)
    if len(msg.data) < n * msg.point_step:
        raise ValueError(f'PointCloud2 data has {len(msg.data)} bytes, expected '
                         f'{n * msg.point_step}')
    words = np.frombuffer(msg.data, dtype='<f4', count=n * msg.point_step // 4)
    rows = words.reshape(n, msg.point_step // 4)
    cols = [by_name[k].offset // 4 for k in 'xyz']
    if cols == [cols[0], cols[0] + 1, cols[0] + 2]:
        return np.ascontiguousarray(rows[:, cols[0]:cols[0] + 3])
    return np.ascontiguousarray(rows[:, cols])


def track_status(header: Header, name: str, state: TrackState, quality: PoseQuality | None,
                 reason: str) -> TrackStatus:
    """The ``TrackStatus`` of one object for one processed cloud."""
    msg = TrackStatus(header=header, object_name=name, state=int(state), reason=reason)
    if quality is not None:
        msg.quality = float(quality.quality)
        msg.inlier_fraction = float(quality.inlier_fraction)
        msg.visible_residual = float(quality.visible_residual) \
            if np.isfinite(quality.visible_residual) else float('nan')
        msg.prediction_error = float(quality.prediction_error)
    return msg
