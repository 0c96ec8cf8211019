"""
Messages <-> arrays for ip_modeler (what the shared ``stereo_manip_tools.conversions`` lacks).

* :func:`model_to_msg` / :func:`msg_to_model`: ``stereo_manip_msgs/ImplicitPolynomial``;
* :func:`mesh_to_marker`: a ``visualization_msgs/Marker`` TRIANGLE_LIST of a zero-set mesh;
* :func:`cloud_to_points`: xyz (and normals when present) of a ``PointCloud2``, counting the
  rows dropped for non-finite coordinates instead of dropping them silently.
"""

from __future__ import annotations

from typing import Optional, Tuple

from geometry_msgs.msg import Point
from ip_modeler.fitting import ImplicitPolynomialModel
from ip_modeler.monomials import MONOMIAL_ORDER
import numpy as np
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import ColorRGBA, Header
from stereo_manip_msgs.msg import ImplicitPolynomial
from stereo_manip_tools.conversions import DEFAULT_MAX_ABS_COORDINATE, read_pointcloud2
from visualization_msgs.msg import Marker

__all__ = ['model_to_msg', 'msg_to_model', 'mesh_to_marker', 'cloud_to_points']

NORMAL_FIELDS = ('normal_x', 'normal_y', 'normal_z')


def model_to_msg(model: ImplicitPolynomialModel, header: Header, *, rms_distance: float,
                 max_distance: float, point_count: int) -> ImplicitPolynomial:
    """Make the ImplicitPolynomial message of a fitted model (distances [m], true geometric)."""
    msg = ImplicitPolynomial(header=header)
    msg.degree = int(model.degree)
    msg.monomial_order = MONOMIAL_ORDER
    msg.coefficients = [float(c) for c in model.coefficients]
    msg.centre = Point(x=float(model.centre[0]), y=float(model.centre[1]),
                       z=float(model.centre[2]))
    msg.scale = float(model.scale)
    msg.rms_distance = float(rms_distance)
    msg.max_distance = float(max_distance)
    msg.point_count = int(point_count)
    msg.method = model.method
    msg.status = model.status
    return msg


def msg_to_model(msg: ImplicitPolynomial) -> ImplicitPolynomialModel:
    """
    Model of an ImplicitPolynomial message.

    :raises ValueError: unknown monomial order, or a coefficient count that does not match the
        degree.
    """
    if msg.monomial_order != MONOMIAL_ORDER:
        raise ValueError(f'monomial_order {msg.monomial_order!r} is not supported '
                         f'(expected {MONOMIAL_ORDER!r})')
    return ImplicitPolynomialModel(
        int(msg.degree), np.asarray(msg.coefficients, dtype=float),
        np.array([msg.centre.x, msg.centre.y, msg.centre.z]), float(msg.scale),
        msg.method, msg.status)


def mesh_to_marker(vertices: np.ndarray, triangles: np.ndarray, header: Header, *,
                   ns: str = 'ip_zero_set', marker_id: int = 0,
                   rgba: Tuple[float, float, float, float] = (0.2, 0.6, 1.0, 0.8)) -> Marker:
    """
    TRIANGLE_LIST marker of a mesh (vertices [m] in ``header.frame_id``).

    An empty mesh gives a DELETE marker, so a stale zero set disappears from RViz.
    """
    m = Marker(header=header, ns=ns, id=int(marker_id))
    if len(triangles) == 0:
        m.action = Marker.DELETE
        return m
    m.type = Marker.TRIANGLE_LIST
    m.action = Marker.ADD
    m.pose.orientation.w = 1.0
    m.scale.x = m.scale.y = m.scale.z = 1.0
    m.color = ColorRGBA(r=float(rgba[0]), g=float(rgba[1]), b=float(rgba[2]),
                        a=float(rgba[3]))
    flat = np.asarray(vertices, dtype=float)[np.asarray(triangles).reshape(-1)]
    m.points = [Point(x=float(x), y=float(y), z=float(z)) for x, y, z in flat]
    return m


def cloud_to_points(msg: PointCloud2, use_normals: bool = True
                    ) -> Tuple[np.ndarray, Optional[np.ndarray], int]:
    """
    Read xyz [m] and, if present and wanted, normals of a cloud; unusable rows are removed.

    The layout is checked by :func:`stereo_manip_tools.conversions.read_pointcloud2`.

    :returns: (points (N, 3), normals (N, 3) or None, number of rows removed because a
        coordinate or normal was NaN/inf, a coordinate exceeded
        ``DEFAULT_MAX_ABS_COORDINATE``, or a normal was zero).
    :raises stereo_manip_tools.conversions.PointCloudError: unreadable layout.
    """
    names = {f.name for f in msg.fields}
    has_normals = use_normals and all(n in names for n in NORMAL_FIELDS)
    fields = ('x', 'y', 'z') + (NORMAL_FIELDS if has_normals else ())
    data = read_pointcloud2(msg, fields, drop_invalid=False).points
    ok = np.all(np.isfinite(data), axis=1)
    with np.errstate(invalid='ignore'):
        ok &= np.all(np.abs(data[:, :3]) <= DEFAULT_MAX_ABS_COORDINATE, axis=1)
    if has_normals:
        ok &= np.linalg.norm(data[:, 3:6], axis=1) > 1e-9
    data = data[ok]
    normals = data[:, 3:6] if has_normals else None
    return data[:, :3], normals, int(np.count_nonzero(~ok))
