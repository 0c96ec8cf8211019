"""
``joint_estimator_node``: joint between two links estimated from their pose tracks.

Input (parameter ``input_mode``, read-only):
  - ``two_links`` (default): ``link_a_pose`` and ``link_b_pose`` (geometry_msgs/PoseStamped in a
    common frame; sensor-data QoS with a queue of 100), paired by stamp within
    ``sync_tolerance`` [s];
  - ``relative``: ``relative_pose`` (PoseStamped of link A in link B's frame).
The relative poses ``^B T_A`` of the last ``window_size`` pairs are kept; every
``estimate_every`` new poses (once ``min_poses`` are in the window) the joint is estimated
(:func:`joint_estimator.selection.estimate_joint`, in the subscription callback: automatic
selection over a 200-pose window takes ~0.1-0.5 s, so raise ``estimate_every`` for fast
streams) and published:
  - ``joint_estimate`` (stereo_manip_msgs/JointEstimate; header frame = link B),
  - ``corrected_pose`` (PoseStamped: newest pose of link A in link B, corrected onto the joint),
  - ``corrected_track`` (nav_msgs/Path: the corrected window),
  - ``joint_marker`` (visualization_msgs/Marker for RViz: the axis as a red line, the
    spherical centre as a sphere, the planar normal as an arrow; deleted for a fixed joint).
Service ``estimate_joint`` (stereo_manip_msgs/EstimateJoint) estimates from a batch.

Defaults suit square-marker tracks from a camera with unknown noise: in relative mode the noise
levels are estimated from the data (``sigma_position`` / ``sigma_rotation`` 0; in two_links mode
they default to 5 mm / 2 deg, see the parameter descriptions), flipped marker poses are
repaired with their ambiguity twin (``flip_repair``; relative mode: link B is the camera, link A
the marker; two_links mode: both links' poses are markers in the camera's frame), and every
estimate reports its noise, inlier coverage, axis uncertainty and warnings.

Bad input (NaN, zero quaternion, stamps going backwards, unpaired poses) is logged with the
reason and counted; the counts are in every JointEstimate's ``status``. A stamp more than
``stamp_reset_threshold`` behind the newest one (a source restart, a bag played in a loop)
clears the window (and the pairing queues), is logged once per event and counted; estimation
resumes once ``min_poses`` new poses have arrived.
"""

from __future__ import annotations

from collections import deque
from typing import List, Optional

from geometry_msgs.msg import PoseStamped
from joint_estimator.ambiguity import AXIS_INDEX, relative_candidates, two_link_candidates
from joint_estimator.common import check_unit_quaternion, JointType, relative_track
from joint_estimator.selection import estimate_joint, JointEstimation
from nav_msgs.msg import Path
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, ParameterType, SetParametersResult
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data, QoSProfile
from std_msgs.msg import ColorRGBA, Header
from stereo_manip_msgs.msg import JointEstimate
from stereo_manip_msgs.srv import EstimateJoint
from stereo_manip_tools.conversions import matrices_to_path, matrix_to_pose, ns_to_stamp, \
    numpy_to_point, numpy_to_vector3, path_to_matrices, pose_stamped_to_matrix
from stereo_manip_tools.diagnostics import NodeDiagnostics
from stereo_manip_tools.parameters import (
    choice_parameter_reason, float_descriptor as _float, int_descriptor as _int,
    reject_nonfinite_parameters, string_descriptor as _string)
from stereo_manip_tools.robustness import create_node_or_exit, InputRejections, \
    spin_until_shutdown
from stereo_manip_tools.sync import StampSynchronizer
from stereo_manip_tools.tf import object_frame, PoseTfPublisher
from visualization_msgs.msg import Marker

__all__ = ['JointEstimatorNode', 'estimation_to_msg', 'estimation_to_marker', 'JOINT_TYPE_NAMES',
           'main']

#: Parameter values of ``joint_type`` and their JointEstimate constants (auto: 255).
JOINT_TYPE_NAMES = {'auto': 255, **{t.name.lower(): int(t) for t in JointType}}


def _check_orientation(msg: PoseStamped) -> None:
    """Reject a pose whose quaternion is not (nearly) unit (see ``check_unit_quaternion``)."""
    q = msg.pose.orientation
    check_unit_quaternion((q.x, q.y, q.z, q.w))


def joint_position(estimation: JointEstimation) -> float:
    """
    Joint coordinate of the newest pose.

    Angle [rad] (revolute, cylindrical, planar), displacement [m] (prismatic), rotation angle [rad]
    (spherical), 0 (fixed).
    """
    best = estimation.best
    if best.coordinates.shape[1] == 0:
        return 0.0
    if best.joint_type == JointType.SPHERICAL:
        return float(np.linalg.norm(best.coordinates[-1]))
    return float(best.coordinates[-1, 0])


def estimation_to_msg(estimation: JointEstimation, header: Header, link_a_frame: str,
                      link_b_frame: str) -> JointEstimate:
    """
    Build the JointEstimate message of an estimation.

    JointEstimate message of an estimation (RMS residuals over the inlier frames; noise,
    coverage, uncertainty and warnings of the selected fit).
    """
    b = estimation.best
    msg = JointEstimate(header=header, joint_type=int(b.joint_type), link_a_frame=link_a_frame,
                        link_b_frame=link_b_frame)
    msg.axis_in_a = numpy_to_vector3(b.axis_in_a)
    msg.axis_in_b = numpy_to_vector3(b.axis_in_b)
    msg.point_in_a = numpy_to_point(b.point_in_a)
    msg.point_in_b = numpy_to_point(b.point_in_b)
    msg.rotation_residual = b.rotation_rms
    msg.position_residual = b.position_rms
    msg.sample_count = int(b.inliers.size)
    msg.outlier_count = int(b.outlier_indices.size)
    msg.candidate_types = [int(t) for t in estimation.candidates]
    msg.candidate_scores = [float(f.score) for f in estimation.candidates.values()]
    msg.repaired_count = int(b.repaired_indices.size)
    msg.rotation_noise = float(b.sigma_rotation)
    msg.position_noise = float(b.sigma_position)
    msg.position_noise_ray_ratio = float(b.extra.get('line_of_sight_noise_ratio', 1.0))
    msg.noise_estimated = bool(b.scale_estimated)
    msg.inlier_coordinate_min, msg.inlier_coordinate_max = (float(v)
                                                            for v in b.coordinate_range)
    msg.motion_coordinate_min, msg.motion_coordinate_max = (float(v) for v in b.motion_range)
    msg.inlier_coverage = float(b.coverage)
    msg.axis_angle_std_in_a = float(b.axis_angle_std_in_a)
    msg.axis_angle_std_in_b = float(b.axis_angle_std_in_b)
    msg.axis_point_std = float(b.axis_point_std)
    msg.warnings = [str(w) for w in b.warnings]
    msg.joint_position = joint_position(estimation)
    msg.status = estimation.status
    return msg


def estimation_to_marker(estimation: JointEstimation, header: Header) -> Marker:
    """Make the RViz marker of the estimated joint in link B's frame (see the module docstring)."""
    b = estimation.best
    m = Marker(header=header, ns='joint_estimator', id=0, action=Marker.ADD,
               color=ColorRGBA(r=1.0, g=0.0, b=0.0, a=1.0))
    m.pose.orientation.w = 1.0
    p = b.corrected[:, :3, 3]
    if b.joint_type in (JointType.REVOLUTE, JointType.CYLINDRICAL, JointType.PRISMATIC):
        s = (p - b.point_in_b) @ b.axis_in_b
        m.type, m.scale.x = Marker.LINE_LIST, 0.005
        m.points = [numpy_to_point(b.point_in_b + v * b.axis_in_b)
                    for v in (s.min() - 0.1, s.max() + 0.1)]
    elif b.joint_type == JointType.SPHERICAL:
        m.type = Marker.SPHERE
        m.scale.x = m.scale.y = m.scale.z = 0.02
        m.pose.position = numpy_to_point(b.point_in_b)
    elif b.joint_type == JointType.PLANAR:
        m.type, m.scale.x, m.scale.y, m.scale.z = Marker.ARROW, 0.005, 0.01, 0.02
        c = p.mean(axis=0)
        m.points = [numpy_to_point(c), numpy_to_point(c + 0.1 * b.axis_in_b)]
    else:
        m.action = Marker.DELETE
    return m


class JointEstimatorNode(Node):
    """Sliding-window joint estimation; thin wrapper around :mod:`joint_estimator.selection`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('joint_estimator', **kwargs)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        reject_nonfinite_parameters(self)
        self.rejections = InputRejections(self.get_logger())
        guard = self.rejections.guard
        self.declare_parameter('input_mode', 'two_links', _string(
            "'two_links' (link_a_pose + link_b_pose in a common frame) or 'relative' "
            '(relative_pose: link A in link B)', read_only=True))
        self.declare_parameter('link_a_frame', 'link_a', _string("name of link A's frame"))
        self.declare_parameter('link_b_frame', '', _string(
            "name of link B's frame (frame_id of the outputs); empty: relative_pose's "
            "frame_id (relative mode) or 'link_b'"))
        self.declare_parameter('window_size', 200, _int(
            'relative poses kept in the sliding window', 3, 100000, read_only=True))
        self.declare_parameter('min_poses', 10, _int(
            'poses needed in the window before estimating', 2, 100000))
        self.declare_parameter('estimate_every', 5, _int(
            'estimate after every this many new poses', 1, 100000))
        self.declare_parameter('joint_type', 'auto', _string(
            'joint type to fit: auto (BIC selection), fixed, revolute, prismatic, spherical, '
            'cylindrical or planar'))
        # relative mode (a marker seen by the camera B): noise estimated from the data, with the
        # camera's line-of-sight noise model. two_links mode: the relative positions are not
        # seen along one line of sight, and with estimated noise a planar joint absorbs the
        # depth noise of stereo-localised links (measured in the revolute_pair demo), so the
        # fixed defaults stay there (set 0 to estimate)
        two_links = self.get_parameter('input_mode').value != 'relative'
        self.declare_parameter('sigma_position', 0.005 if two_links else 0.0, _float(
            'position noise std per axis of the pose tracks [m]; 0: estimated from the data '
            '(default in relative mode; two_links: 0.005)', 0.0, 1.0))
        self.declare_parameter('sigma_rotation', float(np.deg2rad(2.0)) if two_links else 0.0,
                               _float('orientation noise std per axis of the pose tracks [rad]; '
                                      '0: estimated from the data (default in relative mode; '
                                      'two_links: 2 deg)', 0.0, 1.0))
        self.declare_parameter('flip_repair', True, ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description='repair square-marker pose flips with the ambiguity twin (relative '
                        'mode: link B is the camera; two_links: both poses in the camera frame)'))
        self.declare_parameter('marker_normal_axis', 'z', _string(
            "axis of the marker frame that is its normal: 'x', 'y' or 'z' (ArUco: z)"))
        self.declare_parameter('marker_weights', True, ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description='relative mode, estimated noise: refit a revolute joint with each '
                        "frame's own marker-pose noise (depth, tilt; from the corners' geometry)"))
        self.declare_parameter('marker_side', 0.0, _float(
            "the square marker's side [m] for the per-frame noise model; 0: estimated from "
            'the track', 0.0, 10.0))
        self.declare_parameter('stamp_reset_threshold', 0.5, _float(
            'a stamp this far behind the newest [s] is a source restart: the window is cleared',
            0.0, 1e6))
        self.declare_parameter('robust', True, ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description='reject outlier frames (MSAC over minimal sets + refit)'))
        self.declare_parameter('refine', True, ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description='maximum-likelihood refinement of revolute/cylindrical axes; false: '
                        "the chapter's Eqs. 17-18 only"))
        self.declare_parameter('correction', 'ml', _string(
            "corrected track: 'ml' (weighted projection on the joint) or 'chapter' "
            '(revolute: minimal-rotation correction of Section 4)'))
        self.declare_parameter('min_rotation_range', float(np.deg2rad(10.0)), _float(
            'rotation range below which an axis is undefined (degenerate motion) [rad]',
            0.0, np.pi))
        self.declare_parameter('min_translation_range', 0.02, _float(
            'translation range below which a sliding direction is undefined [m]', 0.0, 10.0))
        self.declare_parameter('sync_tolerance', 0.005, _float(
            'largest stamp difference when pairing link_a_pose with link_b_pose [s]', 0.0, 1.0,
            read_only=True))

        self.window: deque = deque(maxlen=int(self.get_parameter('window_size').value))
        self.counts = {'received': 0, 'rejected': 0, 'estimates': 0, 'failed_estimates': 0,
                       'resets': 0}
        self._last_pair_stamp: Optional[int] = None
        self._sync_dropped_before: dict = {}
        self._new_since_estimate = 0
        self._last_b_frame = ''
        self.estimate_pub = self.create_publisher(JointEstimate, 'joint_estimate', 10)
        self.pose_pub = self.create_publisher(PoseStamped, 'corrected_pose', 10)
        self.tf = PoseTfPublisher(self)   # corrected_pose also on /tf as <link_a>_corrected
        self.tf.follow(self.pose_pub, lambda: object_frame(
            self.get_parameter('link_a_frame').value) + '_corrected')
        self.track_pub = self.create_publisher(Path, 'corrected_track', 10)
        self.marker_pub = self.create_publisher(Marker, 'joint_marker', 10)
        self.create_service(EstimateJoint, 'estimate_joint', self._on_service)
        mode = self.get_parameter('input_mode').value
        # sensor-data QoS (best effort, matches any publisher) with room for the poses that
        # arrive while an estimate is being computed
        qos = QoSProfile(depth=100, reliability=qos_profile_sensor_data.reliability,
                         durability=qos_profile_sensor_data.durability,
                         history=qos_profile_sensor_data.history)
        self.sync: Optional[StampSynchronizer] = None
        if mode == 'relative':
            self.create_subscription(PoseStamped, 'relative_pose',
                                     guard(self._on_relative, 'relative_pose'), qos)
        else:
            tol = int(round(self.get_parameter('sync_tolerance').value * 1e9))
            self._sync_tolerance_ns = tol
            self.sync = StampSynchronizer(('a', 'b'), tolerance_ns=tol, queue_size=50)
            self.create_subscription(PoseStamped, 'link_a_pose',
                                     guard(lambda m: self._on_link(m, 'a'), 'link_a_pose'), qos)
            self.create_subscription(PoseStamped, 'link_b_pose',
                                     guard(lambda m: self._on_link(m, 'b'), 'link_b_pose'), qos)
        self.get_logger().info(f'joint_estimator: input {mode}, window '
                               f'{self.window.maxlen}, joint type '
                               f'{self.get_parameter("joint_type").value}')
        self.diagnostics = NodeDiagnostics(self, lambda: {**self.counts, **{  # /diagnostics
            f'unpaired_{k}': v for k, v in (self.sync.dropped if self.sync else {}).items()}})

    # --- parameters -----------------------------------------------------------------------

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        """Check what the descriptors' ranges do not (choices of the string parameters)."""
        reason = choice_parameter_reason(params, {
            'input_mode': ('two_links', 'relative'), 'joint_type': JOINT_TYPE_NAMES,
            'marker_normal_axis': tuple(AXIS_INDEX), 'correction': ('ml', 'chapter')})
        return SetParametersResult(successful=reason is None, reason=reason or '')

    def _estimate(self, poses: np.ndarray, stamps: np.ndarray,
                  joint_type: Optional[int] = None,
                  link_poses: Optional[tuple] = None) -> JointEstimation:
        """
        Estimate with the node's parameters.

        ``link_poses = (A, B)`` (camera frame) in two_links mode, for the flip candidates of both
        links.
        """
        g = self.get_parameter
        if joint_type is None:
            joint_type = JOINT_TYPE_NAMES[g('joint_type').value]
        axis = AXIS_INDEX[g('marker_normal_axis').value]
        flip = bool(g('flip_repair').value)
        candidates = None
        if flip and link_poses is not None:
            candidates = two_link_candidates(link_poses[0], link_poses[1], axis)
        elif flip:
            candidates = relative_candidates(poses, axis)
        return estimate_joint(
            poses, joint_type=joint_type, sigma_position=g('sigma_position').value or None,
            sigma_rotation=g('sigma_rotation').value or None, robust=g('robust').value,
            refine=g('refine').value, correction=g('correction').value,
            min_rotation_range=g('min_rotation_range').value,
            min_translation_range=g('min_translation_range').value, stamps_ns=stamps,
            flip_repair=flip, marker_normal_axis=axis, pose_candidates=candidates,
            # the relative positions of two links are not seen along a camera's line of sight
            camera_noise=link_poses is None, marker_weights=g('marker_weights').value,
            marker_side=g('marker_side').value or None)

    def _b_frame(self) -> str:
        return self.get_parameter('link_b_frame').value or self._last_b_frame or 'link_b'

    # --- streaming input ------------------------------------------------------------------

    def _reject(self, what: str, why: str) -> None:
        self.counts['rejected'] += 1    # counted every time; the warning at most 1/s per input
        self.rejections.reject(what, f'{what} rejected ({self.counts["rejected"]} so far): '
                               f'{why}')

    def _on_link(self, msg: PoseStamped, key: str) -> None:
        self.counts['received'] += 1
        try:
            T, stamp, frame = pose_stamped_to_matrix(msg)
            _check_orientation(msg)
        except ValueError as exc:
            self._reject(f'link_{key}_pose', str(exc))
            return
        del frame     # the common frame; link B's own frame name is link_b_frame
        if (self._last_pair_stamp is not None
                and stamp < self._last_pair_stamp - self._reset_threshold_ns()):
            self._reset(f'link_{key}_pose', stamp, self._last_pair_stamp)
        pair = self.sync.add(key, stamp, (T, stamp))
        if pair is not None:
            T_a, T_b = pair['a'][0], pair['b'][0]
            T_rel = relative_track(T_a[None], T_b[None])[0]
            stamp_pair = max(pair['a'][1], pair['b'][1])
            self._last_pair_stamp = stamp_pair
            self._add(T_rel, stamp_pair, (T_a, T_b))

    def _on_relative(self, msg: PoseStamped) -> None:
        self.counts['received'] += 1
        try:
            T, stamp, frame = pose_stamped_to_matrix(msg)
            _check_orientation(msg)
        except ValueError as exc:
            self._reject('relative_pose', str(exc))
            return
        self._last_b_frame = frame
        self._add(T, stamp)

    def _reset_threshold_ns(self) -> int:
        return int(round(self.get_parameter('stamp_reset_threshold').value * 1e9))

    def _reset(self, what: str, stamp: int, newest: int) -> None:
        """
        Handle a source restart (stamps jumped back).

        Clear the window and the pairing queues; one log line per event.
        """
        self.counts['resets'] += 1
        self.get_logger().warning(
            f'{what}: stamp {stamp} ns is {(newest - stamp) / 1e9:.3f} s behind the newest '
            f'({newest} ns): source restarted; window of {len(self.window)} poses cleared '
            f'(reset {self.counts["resets"]}), estimating again after '
            f'{self.get_parameter("min_poses").value} poses')
        self.window.clear()
        self._new_since_estimate = 0
        self._last_pair_stamp = None
        if self.sync is not None:
            for k, v in self.sync.dropped.items():
                self._sync_dropped_before[k] = self._sync_dropped_before.get(k, 0) + v
            self.sync = StampSynchronizer(('a', 'b'), tolerance_ns=self._sync_tolerance_ns,
                                          queue_size=50)

    def _add(self, T: np.ndarray, stamp: int, link_poses: Optional[tuple] = None) -> None:
        if self.window and stamp <= self.window[-1][0]:
            if stamp < self.window[-1][0] - self._reset_threshold_ns():
                self._reset('pose', stamp, self.window[-1][0])
            else:
                self._reject('pose', f'stamp {stamp} ns is not after the previous one '
                             f'({self.window[-1][0]} ns); stamps must increase')
                return
        self.window.append((stamp, T, link_poses))
        self._new_since_estimate += 1
        g = self.get_parameter
        if (len(self.window) >= g('min_poses').value
                and self._new_since_estimate >= g('estimate_every').value):
            self._new_since_estimate = 0
            self._publish_window_estimate()

    def _dropped_summary(self) -> str:
        parts = [f'{self.counts["rejected"]} poses rejected']
        if self.sync is not None:
            dropped = {k: v + self._sync_dropped_before.get(k, 0)
                       for k, v in self.sync.dropped.items()}
            parts.append(f'{sum(dropped.values())} unpaired '
                         f'({", ".join(f"{k} {v}" for k, v in dropped.items())})')
        if self.counts['resets']:
            parts.append(f'{self.counts["resets"]} source restarts (window cleared)')
        return 'input: ' + ', '.join(parts)

    def _publish_window_estimate(self) -> None:
        stamps = np.array([s for s, _, _ in self.window], dtype=np.int64)
        poses = np.array([T for _, T, _ in self.window])
        links = None
        if self.sync is not None and all(lp is not None for _, _, lp in self.window):
            links = (np.array([lp[0] for _, _, lp in self.window]),
                     np.array([lp[1] for _, _, lp in self.window]))
        try:
            est = self._estimate(poses, stamps, link_poses=links)
        except ValueError as exc:
            self.counts['failed_estimates'] += 1
            self.get_logger().warning(f'no estimate from {len(poses)} poses '
                                      f'({self.counts["failed_estimates"]} so far): {exc}')
            return
        self.counts['estimates'] += 1
        header = Header(stamp=ns_to_stamp(int(stamps[-1])), frame_id=self._b_frame())
        msg = estimation_to_msg(est, header, self.get_parameter('link_a_frame').value,
                                header.frame_id)
        msg.status = f'{msg.status}; {self._dropped_summary()}'
        self.estimate_pub.publish(msg)
        self.pose_pub.publish(PoseStamped(header=header,
                                          pose=matrix_to_pose(est.best.corrected[-1])))
        self.track_pub.publish(matrices_to_path(est.best.corrected, header.frame_id, stamps))
        self.marker_pub.publish(estimation_to_marker(est, header))

    # --- service --------------------------------------------------------------------------

    def _on_service(self, request: EstimateJoint.Request,
                    response: EstimateJoint.Response) -> EstimateJoint.Response:
        try:
            T_a, stamps = path_to_matrices(request.link_a)
            if request.link_b.poses:
                T_b, stamps_b = path_to_matrices(request.link_b)
                if T_b.shape != T_a.shape:
                    raise ValueError(f'link_a has {len(T_a)} poses, link_b {len(T_b)}')
                tol = self.get_parameter('sync_tolerance').value * 1e9
                if np.any(np.abs(stamps - stamps_b) > tol):
                    i = int(np.flatnonzero(np.abs(stamps - stamps_b) > tol)[0])
                    raise ValueError(f'stamps of link_a and link_b differ at pose {i} '
                                     f'({stamps[i]} vs {stamps_b[i]} ns)')
                poses = relative_track(T_a, T_b)
                links = (T_a, T_b)
                b_frame = self.get_parameter('link_b_frame').value or 'link_b'
            else:
                poses, links = T_a, None
                b_frame = (self.get_parameter('link_b_frame').value
                           or request.link_a.header.frame_id or 'link_b')
            jt = int(request.joint_type)
            if jt != 255 and jt not in {int(t) for t in JointType}:
                raise ValueError(f'joint_type {jt} is not a JointEstimate constant or AUTO (255)')
            est = self._estimate(poses, stamps, jt, links)
        except ValueError as exc:
            response.success = False
            response.message = str(exc)
            self.get_logger().warning(f'estimate_joint request failed: {exc}')
            return response
        header = Header(stamp=ns_to_stamp(int(stamps[-1])), frame_id=b_frame)
        response.estimate = estimation_to_msg(est, header,
                                              self.get_parameter('link_a_frame').value, b_frame)
        response.corrected_track = matrices_to_path(est.best.corrected, b_frame, stamps)
        response.outlier_indices = [int(i) for i in est.best.outlier_indices]
        response.repaired_indices = [int(i) for i in est.best.repaired_indices]
        if est.best.coordinates.shape[1] and est.best.joint_type != JointType.SPHERICAL:
            response.coordinates = [float(v) for v in est.best.coordinates[:, 0]]
        response.success = True
        response.message = est.status
        return response


def main(args=None) -> None:
    """Run the node."""
    rclpy.init(args=args)
    node = create_node_or_exit(JointEstimatorNode, 'joint_estimator_node')
    spin_until_shutdown(node)
