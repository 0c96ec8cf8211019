"""
``ip_modeler_node``: implicit-polynomial model of a segmented object cloud (Section 5).

Subscribes ``cloud`` (sensor_msgs/PointCloud2 of one object, sensor-data QoS; normals are used
when the cloud has ``normal_x/normal_y/normal_z`` and ``use_cloud_normals`` is true, otherwise
estimated and oriented toward ``viewpoint``). Each cloud is fitted with the adaptive-degree 3L
fit by incremental QR (:func:`ip_modeler.fitting.fit_implicit_polynomial`) and published as

  - ``implicit_polynomial`` (stereo_manip_msgs/ImplicitPolynomial, in the cloud's frame, with
    the true RMS/max distance of the points to the zero set),
  - ``zero_set_marker`` (visualization_msgs/Marker TRIANGLE_LIST: the zero set inside the
    cloud's bounding box, by marching cubes).

Service ``fit_implicit_polynomial`` (stereo_manip_msgs/FitImplicitPolynomial) fits a cloud on
request (``max_degree``/``target_rms`` of 0 mean the node's parameters).

Fit rate: ``min_fit_interval_s`` bounds how often the node fits (a cloud that arrives sooner
after the start of the previous fit is skipped and counted, never queued), so in a live graph the
modeller's CPU share is at most about (fit CPU time) / ``min_fit_interval_s`` and it cannot
starve the pose path: its output rate is then a design figure, about 1 / max(interval, fit
time). ``warm_start`` starts each fit's degree search one below the previous fit's degree (the
lower degrees are only factorised, not checked for spurious sheets nor selectable).
``refit_ratio`` > 0: a cloud that the last streamed model still fits (the RMS and the 95th
percentile of the first-order distance of its points to the zero set at most ``refit_ratio``
times those of the points the model was fitted to) is not fitted again and nothing is published
(counted as ``skipped_unchanged``; the last model stands): an object that has not changed in
the cloud's frame (static, or turning about its own symmetry axis) costs one evaluation of the
polynomial per cloud the interval lets through (~10-25 ms for 2000 points) instead of a fit
(0.3-0.6 s CPU).

CPU share: ``nice`` > 0 lowers the node's scheduling priority at start-up (``os.nice``): a fit
(0.3-0.6 s of CPU in one go) then yields the cores to the pose path (camera, stereo,
localiser) whenever those have work, instead of taking an equal share of them, and runs in
the time they leave.

Bad input (empty cloud, NaN points, too few points for the degree, planar or collinear clouds)
is logged with the reason and counted; the node keeps running. Counts appear in every
message's ``status``.
"""

from __future__ import annotations

import os
import time
from typing import Dict, List, Optional, Tuple

from ip_modeler.conversions import cloud_to_points, mesh_to_marker, model_to_msg
from ip_modeler.evaluation import bounding_region, distance_to_zero_set, zero_set_mesh
from ip_modeler.fitting import DEFAULT_3L_OFFSET, estimate_normals, fit_implicit_polynomial, \
    ImplicitPolynomialModel, MAX_SUPPORTED_DEGREE
from ip_modeler.incremental_qr import STABILIZATION_MODES
from ip_modeler.monomials import monomial_count
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, ParameterType, SetParametersResult
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2
from stereo_manip_msgs.msg import ImplicitPolynomial
from stereo_manip_msgs.srv import FitImplicitPolynomial
from stereo_manip_tools.diagnostics import NodeDiagnostics
from stereo_manip_tools.parameters import choice_parameter_reason, \
    float_descriptor as _float, INPUT_QOS_CHOICES, input_qos_descriptor, input_qos_profile, \
    int_descriptor as _int, reject_nonfinite_parameters
from stereo_manip_tools.robustness import create_node_or_exit, InputRejections, \
    spin_until_shutdown
from visualization_msgs.msg import Marker

__all__ = ['IpModelerNode', 'main']


class IpModelerNode(Node):
    """Fits implicit polynomials to object clouds; thin wrapper around :mod:`ip_modeler`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('ip_modeler', **kwargs)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        reject_nonfinite_parameters(self)
        self.declare_parameter('max_degree', 8, _int(
            'highest polynomial degree tried', 1, MAX_SUPPORTED_DEGREE))
        self.declare_parameter('target_rms', 0.001, _float(
            'stop raising the degree once the RMS first-order distance of the points to the '
            'zero set is at most this [m]; 0: go to max_degree and keep the best', 0.0, 10.0))
        self.declare_parameter('offset', DEFAULT_3L_OFFSET, _float(
            '3L layer offset c along the normals, as a fraction of the normalisation scale',
            0.001, 0.45))
        self.declare_parameter('stabilization', 'drop', ParameterDescriptor(
            type=ParameterType.PARAMETER_STRING,
            description="columns with a small R diagonal: 'drop', 'ridge' or 'none'"))
        self.declare_parameter('stability_tol', 1e-6, _float(
            'R-diagonal threshold (relative to the largest column norm) for unstable columns',
            0.0, 0.1))
        self.declare_parameter('ridge', 1e-6, _float(
            'global ridge-regression weight on the non-constant coefficients (0: plain LS)',
            0.0, 1.0))
        self.declare_parameter('min_improvement', 0.05, _float(
            'relative RMS decrease a degree must bring to count as progress', 0.0, 1.0))
        self.declare_parameter('patience', 3, _int(
            'stop after this many degrees without progress', 1, MAX_SUPPORTED_DEGREE))
        self.declare_parameter('use_cloud_normals', True, ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description='use normal_x/y/z fields of the cloud when present'))
        self.declare_parameter('normal_neighbours', 16, _int(
            'neighbours for PCA normal estimation', 3, 500))
        self.declare_parameter('viewpoint', [0.0, 0.0, 0.0], ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY,
            description='sensor position [m] in the cloud frame, for orienting estimated '
                        'normals outward (optical frame: the origin)'))
        self.declare_parameter('input_qos', 'sensor_data', input_qos_descriptor('cloud'))
        self.declare_parameter('max_points', 5000, _int(
            'clouds with more points are randomly subsampled to this many (counted)',
            10, 10_000_000))
        self.declare_parameter('mesh_resolution', 48, _int(
            'marching-cubes samples along the longest side of the marker box', 8, 256))
        self.declare_parameter('min_fit_interval_s', 0.0, _float(
            'clouds arriving less than this [s, steady clock] after the start of the previous '
            'fit are skipped (counted), so the fit CPU share is at most about fit time / '
            'interval; 0: fit every cloud', 0.0, 3600.0))
        self.declare_parameter('refit_ratio', 0.0, _float(
            'a cloud whose RMS and 95th-percentile first-order distance to the last streamed '
            "model's zero set are at most this times those of the model's own points is not "
            'refitted (counted; nothing published: the last model stands); 0: fit every cloud '
            'the interval lets through', 0.0, 100.0))
        self.declare_parameter('warm_start', False, ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description="start the degree search one below the previous cloud fit's degree "
                        '(lower degrees only factorised, not selectable); service requests '
                        'always search from degree 1'))

        self.declare_parameter('nice', 0, _int(
            "added to the process' nice value at start-up (lower scheduling priority: fits "
            'yield the CPU to the nodes of the pose path); 0: unchanged', 0, 19,
            read_only=True))
        self.niceness = self._lower_priority(self.get_parameter('nice').value)
        self.counts: Dict[str, int] = {'clouds': 0, 'fitted': 0, 'rejected': 0,
                                       'nonfinite_points_dropped': 0,
                                       'points_subsampled_away': 0,
                                       'skipped_min_interval': 0, 'skipped_unchanged': 0}
        self._last_fit_start: Optional[float] = None   # steady clock [s]
        self._last_degree: Optional[int] = None          # of the last streamed fit
        # the last streamed model and (RMS, p95) of its first-order distance on its own points
        self._last_model: Optional[ImplicitPolynomialModel] = None
        self._last_spread: Tuple[float, float] = (0.0, 0.0)
        # (model, points) of the last fit_cloud call
        self._fitted: Optional[Tuple[ImplicitPolynomialModel, np.ndarray]] = None
        self._rng = np.random.default_rng(0)
        self.poly_pub = self.create_publisher(ImplicitPolynomial, 'implicit_polynomial', 10)
        self.marker_pub = self.create_publisher(Marker, 'zero_set_marker', 10)
        self.rejections = InputRejections(self.get_logger())
        self.create_subscription(PointCloud2, 'cloud',
                                 self.rejections.guard(self._on_cloud, 'cloud'),
                                 input_qos_profile(self.get_parameter('input_qos').value))
        self.create_service(FitImplicitPolynomial, 'fit_implicit_polynomial',
                            self.rejections.guard(self._on_service, 'fit_implicit_polynomial',
                                                  default=self._failed_response))
        self.get_logger().info(
            f'ip_modeler: max degree {self.get_parameter("max_degree").value}, target RMS '
            f'{self.get_parameter("target_rms").value} m, nice {self.niceness}')
        self.diagnostics = NodeDiagnostics(self, self.counts)  # /diagnostics: topics, counters

    # --- parameters -----------------------------------------------------------------------

    def _lower_priority(self, increment: int) -> int:
        """Add ``increment`` to this process' nice value; return the nice value."""
        if increment <= 0:
            return os.nice(0)
        try:
            return os.nice(int(increment))
        except OSError as exc:      # not permitted here: run at the normal priority
            self.get_logger().warning(f'nice {increment} not applied: {exc}')
            return os.nice(0)

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        """Check what the descriptors' ranges do not."""
        reason = choice_parameter_reason(params, {'input_qos': INPUT_QOS_CHOICES,
                                                  'stabilization': STABILIZATION_MODES})
        if reason:
            return SetParametersResult(successful=False, reason=reason)
        for p in params:
            if p.name == 'viewpoint':
                v = list(p.value) if p.value is not None else []
                if len(v) != 3 or not np.all(np.isfinite(v)):
                    return SetParametersResult(
                        successful=False,
                        reason=f'viewpoint must be 3 finite numbers [m], got {v}')
        return SetParametersResult(successful=True)

    # --- fitting --------------------------------------------------------------------------

    def _status_counts(self) -> str:
        return (', '.join(f'{k} {v}' for k, v in self.counts.items())
                + f' (rejected by reason: {self.rejections.summary()})')

    def _read_points(self, msg: PointCloud2) -> Tuple[np.ndarray, Optional[np.ndarray]]:
        """
        Return the cloud's finite points (N, 3) [m] and normals (or None), at most max_points.

        :raises ValueError: bad cloud, with the reason.
        """
        g = lambda name: self.get_parameter(name).value  # noqa: E731
        points, normals, dropped = cloud_to_points(msg, g('use_cloud_normals'))
        if dropped:
            self.counts['nonfinite_points_dropped'] += dropped
            self.get_logger().warning(
                f'cloud: dropped {dropped} points with NaN/inf coordinates or normals '
                f'({self.counts["nonfinite_points_dropped"]} so far)')
        if len(points) == 0:
            raise ValueError('cloud has no finite points')
        if len(points) > g('max_points'):
            keep = np.sort(self._rng.choice(len(points), g('max_points'), replace=False))
            self.counts['points_subsampled_away'] += len(points) - len(keep)
            points = points[keep]
            normals = normals[keep] if normals is not None else None
        return points, normals

    def fit_cloud(self, msg: PointCloud2, max_degree: int = 0, target_rms: float = 0.0,
                  min_degree: int = 1, points: Optional[Tuple[np.ndarray,
                                                              Optional[np.ndarray]]] = None
                  ) -> Tuple[ImplicitPolynomial, Marker]:
        """
        Fit one cloud; returns the messages to publish.

        :param min_degree: lowest degree searched (capped at the maximum degree).
        :param points: the cloud's (points, normals) already read by ``_read_points``.

        :raises ValueError: bad cloud or request, with the reason.
        """
        g = lambda name: self.get_parameter(name).value  # noqa: E731
        points, normals = self._read_points(msg) if points is None else points
        if normals is None:
            normals = estimate_normals(points, k=g('normal_neighbours'),
                                       viewpoint=np.asarray(g('viewpoint'), dtype=float))
        max_degree = int(max_degree) or int(g('max_degree'))
        if not 1 <= max_degree <= MAX_SUPPORTED_DEGREE:
            raise ValueError(f'max_degree must be in [1, {MAX_SUPPORTED_DEGREE}], got '
                             f'{max_degree}')
        target = float(target_rms) or float(g('target_rms'))
        start = max(1, min(int(min_degree), max_degree))
        while start > 1 and monomial_count(start) > len(points):   # a small cloud
            start -= 1
        result = fit_implicit_polynomial(
            points, normals, max_degree=max_degree, target_rms=target, offset=g('offset'),
            stabilization=g('stabilization'), stability_tol=g('stability_tol'),
            ridge=g('ridge'), min_improvement=g('min_improvement'), patience=g('patience'),
            min_degree=start)
        model = result.model
        mesh = zero_set_mesh(model, *bounding_region(points, 0.1),
                             resolution=g('mesh_resolution'))
        d = distance_to_zero_set(model, points, mesh=mesh)
        d = d[np.isfinite(d)] if np.any(np.isfinite(d)) else np.array([np.inf])
        self.counts['fitted'] += 1
        model.status = f'{model.status}; {self._status_counts()}'
        poly = model_to_msg(model, msg.header, rms_distance=float(np.sqrt(np.mean(d ** 2))),
                            max_distance=float(d.max()), point_count=len(points))
        marker = mesh_to_marker(*mesh, msg.header)
        self._fitted = (model, points)
        return poly, marker

    @staticmethod
    def _distance_spread(model: ImplicitPolynomialModel, points: np.ndarray
                         ) -> Tuple[float, float]:
        """RMS and 95th percentile [m] of the first-order distance of points to the zero set."""
        d = model.first_order_distance(points)
        d = d[np.isfinite(d)]
        if not len(d):
            return float('inf'), float('inf')
        return float(np.sqrt(np.mean(d ** 2))), float(np.percentile(d, 95))

    def _unchanged(self, points: np.ndarray) -> bool:
        """Tell whether the last streamed model still fits ``points`` (see ``refit_ratio``)."""
        ratio = self.get_parameter('refit_ratio').value
        if ratio <= 0 or self._last_model is None:
            return False
        rms, p95 = self._distance_spread(self._last_model, points)
        return rms <= ratio * self._last_spread[0] and p95 <= ratio * self._last_spread[1]

    def _on_cloud(self, msg: PointCloud2) -> None:
        self.counts['clouds'] += 1
        now = time.monotonic()
        interval = self.get_parameter('min_fit_interval_s').value
        if self._last_fit_start is not None and now - self._last_fit_start < interval:
            self.counts['skipped_min_interval'] += 1
            return
        self._last_fit_start = now
        start = 1
        if self.get_parameter('warm_start').value and self._last_degree is not None:
            start = max(1, self._last_degree - 1)
        try:
            points = self._read_points(msg)
            if self._unchanged(points[0]):
                self.counts['skipped_unchanged'] += 1
                return
            poly, marker = self.fit_cloud(msg, min_degree=start, points=points)
        except ValueError as exc:
            self.counts['rejected'] += 1
            self.rejections.reject(getattr(exc, 'reason', 'unusable_cloud'),
                                   f'cloud {self.counts["clouds"]} rejected: {exc}')
            return
        self._last_degree = int(poly.degree)
        if self.get_parameter('refit_ratio').value > 0:
            self._last_model, fitted = self._fitted
            self._last_spread = self._distance_spread(self._last_model, fitted)
        self.poly_pub.publish(poly)
        self.marker_pub.publish(marker)
        self.get_logger().info(
            f'fitted degree {poly.degree} to {poly.point_count} points: RMS distance '
            f'{poly.rms_distance * 1e3:.2f} mm, max {poly.max_distance * 1e3:.2f} mm')

    def _failed_response(self, request: FitImplicitPolynomial.Request,
                         response: FitImplicitPolynomial.Response, exc: Exception
                         ) -> FitImplicitPolynomial.Response:
        response.success = False
        response.message = f'{type(exc).__name__}: {exc}'
        return response

    def _on_service(self, request: FitImplicitPolynomial.Request,
                    response: FitImplicitPolynomial.Response
                    ) -> FitImplicitPolynomial.Response:
        try:
            if request.target_rms < 0 or not np.isfinite(request.target_rms):
                raise ValueError(f'target_rms must be finite and >= 0, got '
                                 f'{request.target_rms}')
            poly, marker = self.fit_cloud(request.cloud, request.max_degree,
                                          request.target_rms)
        except ValueError as exc:
            self.counts['rejected'] += 1
            self.get_logger().warning(f'fit_implicit_polynomial request rejected: {exc}')
            response.success = False
            response.message = str(exc)
            return response
        self.marker_pub.publish(marker)
        response.model = poly
        response.success = True
        response.message = (f'degree {poly.degree}, RMS distance {poly.rms_distance:.6g} m, '
                            f'{poly.point_count} points')
        return response


def main(args: Optional[List[str]] = None) -> None:
    """Run the node (bad start-up parameters: one line on stderr, exit code 1)."""
    rclpy.init(args=args)
    node = create_node_or_exit(IpModelerNode, 'ip_modeler_node')
    spin_until_shutdown(node)
