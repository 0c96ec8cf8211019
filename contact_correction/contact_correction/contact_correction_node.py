"""
``contact_correction_node``: correct a moving object's observed pose with contact relations.

Subscriptions (geometry_msgs/PoseStamped, sensor-data QoS, poses in a common frame):
  - ``moving_pose``: observed pose of the moving object (e.g. the peg);
  - ``fixed_pose``: pose of the fixed object (the newest one is used); or set the parameter
    ``fixed_pose_static`` ([x, y, z, qx, qy, qz, qw]) for a fixed object that does not move.
Publications, one set per ``moving_pose`` message:
  - ``corrected_pose`` (PoseStamped, the input frame): the corrected pose, or the observed pose
    unchanged when no correction applies (``ContactState.corrected`` false, status says why);
  - ``contact_state`` (stereo_manip_msgs/ContactState, header frame = ``fixed_frame``): the
    relation, ranks, constrained / free directions, penetration, residual, status;
  - ``corrected_track`` (nav_msgs/Path): the last ``track_length`` output poses.
Publication ``smoothing_lag`` frames late (fixed-lag smoothing; while it has subscribers):
  - ``corrected_pose_smoothed`` (PoseStamped, the input's header): each frame corrected with
    the relation the temporal model's back-tracking chooses once the ``smoothing_lag`` frames
    after it are in (a contact released or made is then seen at its first frame; online it
    is held a frame or two longer). Waiting frames are published at once when no
    ``moving_pose`` arrives for ``smoothing_timeout`` seconds, when the stamps go back, and
    when a parameter of the correction changes.
Service ``correct_trajectory`` (stereo_manip_msgs/CorrectTrajectory) corrects a batch.

The relation of each frame is recognised (``recognition`` true: model selection against the
stated pose noise ``sigma_translation`` / ``sigma_rotation`` and an online temporal model over
the stream, :class:`contact_correction.trajectory.ContactCorrector`; the service back-tracks
its whole batch), given (``relation``) or detected per frame with ``tolerance``.
``contact_state`` and ``corrected_track`` are built only while they have subscribers; the track
keeps at most ``track_length`` poses.

Bad input (NaN or zero quaternions, no fixed pose yet) is logged with the reason and counted;
the counts are appended to every ContactState status.
"""

from __future__ import annotations

from collections import deque
import time
from typing import Dict, List, Tuple

from contact_correction.contact_relation import parse_relation
from contact_correction.conversions import contact_state_msg
from contact_correction.correction import correct_pose, CorrectionResult
from contact_correction.polyhedron import check_model_units, load_polyhedron, Polyhedron
from contact_correction.recognition import RecognitionOptions
from contact_correction.trajectory import ContactCorrector, correct_trajectory
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, ParameterType, SetParametersResult
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from std_msgs.msg import Header
from stereo_manip_msgs.msg import ContactState
from stereo_manip_msgs.srv import CorrectTrajectory
from stereo_manip_tools.conversions import matrices_to_path, matrix_to_pose, ns_to_stamp, \
    path_to_matrices, pose_stamped_to_matrix
from stereo_manip_tools.diagnostics import NodeDiagnostics
from stereo_manip_tools.parameters import bool_descriptor as _bool, \
    float_descriptor as _float, int_descriptor as _int, reject_nonfinite_parameters, \
    string_descriptor as _string
from stereo_manip_tools.robustness import create_node_or_exit, InputRejections, \
    spin_until_shutdown
from stereo_manip_tools.tf import object_frame, PoseTfPublisher
from stereo_manip_tools.transforms import pose_from_xyz_quaternion

__all__ = ['ContactCorrectionNode', 'main', 'model_path_problem']

_RECOGNITION_PARAMETERS = ('recognition', 'sigma_translation', 'sigma_rotation',
                           'search_margin', 'free_dof_penalty', 'switch_cost',
                           'transition_cost', 'ambiguity_margin', 'evidence_chi2',
                           'innovation_evidence_chi2', 'max_correction_sigma',
                           'noise_correlation', 'optimal',
                           'tolerance', 'penetration_tolerance', 'angle_tolerance',
                           'max_translation', 'max_rotation', 'check_penetration',
                           'element_margin', 'reference_point')

#: values of the ``reference_point`` parameter
REFERENCE_POINTS = ('origin', 'centroid')


def model_path_problem(value: str) -> str:
    """
    Why a model parameter cannot be used ('' when it can).

    empty, or a path that exists but is not a regular file (a FIFO would block the read, a
    directory fails it).
    """
    if not value.strip():
        return 'must name a model or a model file'
    from pathlib import Path
    path = Path(value)
    try:
        if path.exists() and not path.is_file():
            return f'{value} exists but is not a regular file (FIFO, device or directory)'
    except OSError as exc:
        return f'{value}: {exc}'
    return ''


def static_pose(values: List[float]) -> np.ndarray:
    """
    4x4 pose of ``[x, y, z, qx, qy, qz, qw]`` (metres, unit quaternion).

    :raises ValueError: wrong length, non-finite values or a zero quaternion.
    """
    return pose_from_xyz_quaternion(values, 'fixed_pose_static')


class ContactCorrectionNode(Node):
    """
    Contact-based correction of object poses, streaming and as a service.

    Streaming and batch contact-based correction; thin wrapper around
    :func:`contact_correction.correction.correct_pose`.
    """

    def __init__(self, **kwargs) -> None:
        super().__init__('contact_correction', **kwargs)
        # reset by the parameter callback, which runs from the first declaration on
        self.corrector: ContactCorrector | None = None
        self.smoother: ContactCorrector | None = None     # the fixed-lag one
        self.add_on_set_parameters_callback(self._on_set_parameters)
        reject_nonfinite_parameters(self)
        self.rejections = InputRejections(self.get_logger())
        self.declare_parameter('moving_object', 'peg', _string(
            'model name (or OBJ/PLY/STL path) of the moving object', read_only=True))
        self.declare_parameter('fixed_object', 'hole_block', _string(
            'model name (or OBJ/PLY/STL path) of the fixed object', read_only=True))
        self.declare_parameter('fixed_frame', '', _string(
            "frame_id of ContactState (the fixed object's model frame); empty: fixed_object"))
        static_desc = ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY, read_only=True,
            description='[x y z qx qy qz qw] of a fixed object that does not move (in the '
                        "moving poses' frame); not set: use the fixed_pose topic")
        self.declare_parameter('fixed_pose_static', Parameter.Type.DOUBLE_ARRAY, static_desc)
        self.declare_parameter('tolerance', 0.002, _float(
            'contact detection distance [m]', 0.0, 0.1))
        self.declare_parameter('penetration_tolerance', 0.002, _float(
            'deepest interpenetration still counted as contact when detecting [m]', 0.0, 0.1))
        self.declare_parameter('angle_tolerance', 0.1, _float(
            'angular slack of the local separation test [rad]', 0.0, 0.5))
        self.declare_parameter('optimal', True, _bool(
            'apply the optimal linear correction (Eqs. 2-9) after the non-linear step'))
        self.declare_parameter('max_translation', 0.02, _float(
            'largest accepted correction of the moving origin [m]; larger: passed through',
            0.0, 1.0))
        self.declare_parameter('max_rotation', 0.35, _float(
            'largest accepted orientation correction [rad]; larger: passed through',
            0.0, np.pi))
        self.declare_parameter('check_penetration', True, _bool(
            'measure penetration before and after correction (refuse to output a pose that '
            'still interpenetrates)'))
        self.declare_parameter('track_length', 500, _int(
            'poses kept in corrected_track (built only while it has subscribers)', 1, 10000,
            read_only=True))
        self.declare_parameter('recognition', True, _bool(
            'recognise the relation (model selection against the stated pose noise + temporal '
            'model over the track); false: detect it per frame with `tolerance`'))
        self.declare_parameter('sigma_translation', 0.001, _float(
            'stated pose noise of the moving object relative to the fixed one, translation '
            'per axis [m] (1 sigma)', 1e-6, 0.1))
        self.declare_parameter('sigma_rotation', float(np.deg2rad(1.0)), _float(
            'stated pose noise, rotation per axis [rad] (1 sigma)', 1e-6, 1.0))
        self.declare_parameter('search_margin', 0.0, _float(
            'margin [m] of the candidate contacts; 0: 3 (sigma_t + sigma_r size / 2)',
            0.0, 0.2))
        self.declare_parameter('free_dof_penalty', 3.0, _float(
            'recognition score cost per degree of freedom a relation leaves free', 0.0, 100.0))
        self.declare_parameter('switch_cost', 5.0, _float(
            'temporal model: score cost per contact switched on or off between frames (on top '
            'of transition_cost)', 0.0, 1000.0))
        self.declare_parameter('transition_cost', 15.0, _float(
            'temporal model: score cost of a change of contact state between frames, once '
            'per change', 0.0, 1000.0))
        self.declare_parameter('ambiguity_margin', 5.0, _float(
            'at a contact change the evidence does not pin down, enforce only the contacts '
            'common to both relations when the other is within this score margin (online: '
            'forward costs; correct_trajectory service: min-marginals); online, a relation with '
            'more constraints scoring better by over one free DOF penalty within it is taken up '
            'at once; 0: off', 0.0, 1000.0))
        self.declare_parameter('evidence_chi2', 9.0, _float(
            "drop constraints of the temporal model's relation that the frame rejects: a "
            'nested relation fitting better by more than this chi2 (1 constraint; same tail '
            'probability for more) is used; 0: off', 0.0, 1000.0))
        self.declare_parameter('innovation_evidence_chi2', 6.63, _float(
            'with noise_correlation > 0, online: drop for a frame the constraints that the '
            'change since the previous frame rejects at this level (a chi2 as evidence_chi2; '
            '6.63 = p 0.01: a miss pulls the part back after a release, a false alarm costs '
            'one frame its correction); 0: off', 0.0, 1000.0))
        self.declare_parameter('max_correction_sigma', 4.0, _float(
            'correction-size guard k: a correction over k sigma_translation or k '
            'sigma_rotation is refused; relations with fewer constraints, then only the '
            'penetration removed, are tried; counted as guarded; 0: off', 0.0, 1000.0))
        self.declare_parameter('noise_correlation', 0.0, _float(
            'frame-to-frame correlation (AR(1) rho) of the pose errors: the correct_trajectory '
            "service's temporal model scores a held relation by the innovation of its noise "
            'estimate; online, a contact the innovation rejects (innovation_evidence_chi2) is '
            'dropped for that frame; 0: independent errors', 0.0, 0.99))
        self.declare_parameter('element_margin', 1e-6, _float(
            'largest distance [m] of a corrected contact point outside its element (given / '
            'detected relations; recognised ones use the search margin)', 0.0, 0.05))
        self.declare_parameter('reference_point', 'origin', _string(
            'the point of the moving object the optimal correction keeps where it was observed '
            "along the directions the relation leaves free: 'origin' (the chapter: the model's "
            "origin) or 'centroid' (its surface centroid: independent of where the model's "
            'origin is; better when the pose errors tilt about the middle of the part, as a '
            'surface-fitting localiser makes them)', additional_constraints=' or '.join(
                REFERENCE_POINTS)))
        self.declare_parameter('smoothing_lag', 3, _int(
            'corrected_pose_smoothed: frames a corrected pose waits for the evidence of the '
            'frames after it (fixed-lag smoothing of the contact relation); 0: not published',
            0, 100))
        self.declare_parameter('smoothing_timeout', 0.5, _float(
            'corrected_pose_smoothed: the frames still waiting are published when no '
            'moving_pose arrives for this long [s]', 0.01, 60.0))
        self.declare_parameter('relation', '', _string(
            "explicit contact relation, e.g. 'vertex 0 - face 4; face 2 - vertex 15; edge 3 - "
            "edge 7'; empty: recognised / detected"))

        g = self.get_parameter
        self.moving: Polyhedron | None = None
        self.fixed: Polyhedron | None = None
        self.model_error = ''
        try:
            for name in ('moving_object', 'fixed_object'):
                reason = model_path_problem(str(g(name).value))
                if reason:
                    raise ValueError(f'{name} refused: {reason}')
            self.moving = load_polyhedron(g('moving_object').value)
            self.fixed = load_polyhedron(g('fixed_object').value)
            for poly in (self.moving, self.fixed):
                for w in check_model_units(poly):
                    self.get_logger().warning(w)
        except (ValueError, FileNotFoundError, OSError) as exc:
            self.model_error = f'models unusable: {exc}'
            self.get_logger().error(f'{self.model_error}; every pose will be passed through')
        self.fixed_T: np.ndarray | None = None
        if self._static_values():
            try:
                self.fixed_T = static_pose(self._static_values())
            except ValueError as exc:
                self.model_error = self.model_error or str(exc)
                self.get_logger().error(f'{exc}; every pose will be passed through')
        self.counts: Dict[str, int] = {'received': 0, 'rejected': 0, 'no_fixed_pose': 0,
                                       'corrected': 0, 'passed_through': 0, 'guarded': 0,
                                       'smoothed': 0}
        self.track: deque = deque(maxlen=int(g('track_length').value))
        self._last_moving = time.monotonic()
        self._units_warned = False
        self._last_stamp: int | None = None
        self.pose_pub = self.create_publisher(PoseStamped, 'corrected_pose', 10)
        self.tf = PoseTfPublisher(self)   # corrected_pose also on /tf as <moving>_corrected
        self.tf.follow(self.pose_pub,
                       lambda: f'{object_frame(g("moving_object").value)}_corrected')
        self.state_pub = self.create_publisher(ContactState, 'contact_state', 10)
        self.track_pub = self.create_publisher(Path, 'corrected_track', 10)
        self.smoothed_pub = self.create_publisher(PoseStamped, 'corrected_pose_smoothed', 10)
        self.create_timer(0.05, self._on_smoothing_timer)
        self.create_subscription(PoseStamped, 'moving_pose',
                                 self.rejections.guard(self._on_moving, 'moving_pose'),
                                 qos_profile_sensor_data)
        if not self._static_values():
            self.create_subscription(PoseStamped, 'fixed_pose',
                                     self.rejections.guard(self._on_fixed, 'fixed_pose'),
                                     qos_profile_sensor_data)
        self.create_service(CorrectTrajectory, 'correct_trajectory', self._on_service)
        self.get_logger().info(
            f'contact_correction: {g("moving_object").value} against '
            f'{g("fixed_object").value}, tolerance {g("tolerance").value} m, optimal '
            f'{g("optimal").value}')
        self.diagnostics = NodeDiagnostics(self, self.counts)  # /diagnostics: topics, counters

    # --- parameters -----------------------------------------------------------------------

    def _static_values(self) -> List[float]:
        p = self.get_parameter_or('fixed_pose_static', None)
        try:
            return list(p.value) if p is not None and p.value is not None else []
        except Exception:  # noqa: BLE001 - uninitialised (no override given): not set
            return []

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        """
        Check what the descriptors' ranges do not.

        Finite numbers, model paths that are regular files (a FIFO or a directory would block or
        fail the read), a parsable relation.
        """
        for p in params:
            if p.type_ == Parameter.Type.DOUBLE and not np.isfinite(p.value):
                return SetParametersResult(successful=False,
                                           reason=f'{p.name} must be finite, got {p.value}')
            if p.name in ('moving_object', 'fixed_object') and not str(p.value).strip():
                return SetParametersResult(successful=False,
                                           reason=f'{p.name} must name a model')
            if p.name == 'reference_point' and p.value not in REFERENCE_POINTS:
                return SetParametersResult(
                    successful=False, reason=f'reference_point must be one of '
                    f'{", ".join(REFERENCE_POINTS)}, got {p.value!r}')
            if p.name == 'relation' and str(p.value).strip():
                try:
                    parse_relation(str(p.value))
                except ValueError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
            if p.name in _RECOGNITION_PARAMETERS or p.name in ('smoothing_lag', 'relation'):
                self.corrector = None          # rebuilt with the new values
                self._flush_smoothed()         # the frames waiting, decided with the old ones
                self.smoother = None
            if p.name == 'fixed_pose_static' and p.value:
                try:
                    static_pose(list(p.value))
                except ValueError as exc:
                    return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    def _options(self) -> dict:
        g = self.get_parameter
        return {'optimal': g('optimal').value, 'tolerance': g('tolerance').value,
                'penetration_tolerance': g('penetration_tolerance').value,
                'angle_tolerance': g('angle_tolerance').value,
                'max_translation': g('max_translation').value,
                'max_rotation': g('max_rotation').value,
                'check_penetration': g('check_penetration').value,
                'element_margin': g('element_margin').value,
                'reference_point': self.moving.centroid
                if g('reference_point').value == 'centroid' and self.moving is not None
                else None}

    def _recognition(self) -> RecognitionOptions | None:
        g = self.get_parameter
        if not g('recognition').value:
            return None
        margin = g('search_margin').value
        return RecognitionOptions(
            sigma_translation=g('sigma_translation').value,
            sigma_rotation=g('sigma_rotation').value,
            search_margin=margin if margin > 0 else None,
            free_dof_penalty=g('free_dof_penalty').value,
            switch_cost=g('switch_cost').value,
            transition_cost=g('transition_cost').value,
            ambiguity_margin=g('ambiguity_margin').value,
            evidence_chi2=g('evidence_chi2').value,
            innovation_evidence_chi2=g('innovation_evidence_chi2').value,
            max_correction_sigma=g('max_correction_sigma').value,
            noise_correlation=g('noise_correlation').value)

    def _relation(self):
        text = str(self.get_parameter('relation').value).strip()
        return parse_relation(text) if text else None

    def _fixed_frame(self) -> str:
        return self.get_parameter('fixed_frame').value or self.get_parameter('fixed_object').value

    def _temporal(self) -> bool:
        """Tell whether the relation is recognised over the track (else per frame)."""
        return not (self.moving is None or self.fixed is None or self.model_error
                    or self._relation() is not None or not self.get_parameter('recognition').value)

    def _correct(self, T_moving: np.ndarray, T_fixed: np.ndarray) -> CorrectionResult:
        if self.moving is None or self.fixed is None or self.model_error:
            return CorrectionResult(T_moving=T_moving, status=self.model_error)
        if not self._temporal():
            relation = self._relation()
            r = correct_pose(self.moving, self.fixed, T_moving, T_fixed, relation,
                             **self._options())
            r.relation_source = 'given' if relation is not None else 'detected'
            return r
        if self.corrector is None:
            self.corrector = ContactCorrector(self.moving, self.fixed, self._recognition(),
                                              **self._options())
        return self.corrector.update(T_moving, T_fixed)

    def _smooth(self, T_moving: np.ndarray, T_fixed: np.ndarray, header: Header,
                online: CorrectionResult) -> None:
        """Feed the fixed-lag corrector; publish the frames it decides."""
        lag = int(self.get_parameter('smoothing_lag').value)
        if lag <= 0 or self.smoothed_pub.get_subscription_count() == 0:
            self.smoother = None        # nobody listens: nothing is waiting to be published
            return
        if not self._temporal():
            # no temporal model (given / detected relation, no models): nothing to wait for
            self._publish_smoothed([(header, online)])
            return
        if self.smoother is None:
            self.smoother = ContactCorrector(self.moving, self.fixed, self._recognition(),
                                             lag=lag, **self._options())
        self._publish_smoothed(self.smoother.push(T_moving, T_fixed, header))

    def _publish_smoothed(self, results: List[Tuple[Header, CorrectionResult]]) -> None:
        for header, r in results:
            self.counts['smoothed'] += 1
            self.smoothed_pub.publish(PoseStamped(header=header, pose=matrix_to_pose(r.T_moving)))

    def _flush_smoothed(self) -> None:
        """Decide and publish the frames waiting in the fixed-lag corrector."""
        if self.smoother is not None:
            self._publish_smoothed(self.smoother.flush())

    def _on_smoothing_timer(self) -> None:
        if self.smoother is not None and self.smoother.pending and time.monotonic() \
                - self._last_moving > self.get_parameter('smoothing_timeout').value:
            self._flush_smoothed()

    # --- streaming input ------------------------------------------------------------------

    def _reject(self, what: str, why: str, key: str = 'rejected') -> None:
        self.counts[key] += 1      # counted every time; the warning at most 1/s per reason
        self.rejections.reject(f'{what}:{key}', f'{what} not corrected ({self.counts[key]} so '
                               f'far): {why}')

    def _on_fixed(self, msg: PoseStamped) -> None:
        try:
            self.fixed_T, _, _ = pose_stamped_to_matrix(msg)
        except ValueError as exc:
            self._reject('fixed_pose', str(exc))

    def _summary(self) -> str:
        c = self.counts
        return (f'input: {c["received"]} received, {c["corrected"]} corrected, '
                f'{c["passed_through"]} passed through, {c["guarded"]} guarded, '
                f'{c["rejected"]} rejected, '
                f'{c["no_fixed_pose"]} without fixed pose')

    def _on_moving(self, msg: PoseStamped) -> None:
        self.counts['received'] += 1
        header = msg.header
        try:
            T, stamp, frame = pose_stamped_to_matrix(msg)
        except ValueError as exc:
            self._reject('moving_pose', str(exc))
            return
        if self.fixed_T is None:
            self._reject('moving_pose', 'no fixed_pose received yet', 'no_fixed_pose')
            return
        if self.moving is not None and not self._units_warned:
            dist = float(np.linalg.norm(np.linalg.solve(self.fixed_T, T)[:3, 3]))
            if dist > 100.0 * max(self.moving.size, 1e-3):
                self._units_warned = True
                self.get_logger().warning(
                    f'moving object {dist:.4g} m from the fixed one ({dist / self.moving.size:.0f}'
                    'x its size): poses in millimetres? (REP 103: metres; warned once)')
        self._last_moving = time.monotonic()
        if self._last_stamp is not None and stamp < self._last_stamp:
            self.get_logger().info('moving_pose stamp went back: contact states reset')
            self._flush_smoothed()
            for c in (self.corrector, self.smoother):
                if c is not None:
                    c.reset()
        self._last_stamp = stamp
        result = self._correct(T, self.fixed_T)
        self.counts['corrected' if result.corrected else 'passed_through'] += 1
        if result.guarded:
            self.counts['guarded'] += 1
            self.get_logger().warning(
                f'correction guarded ({self.counts["guarded"]} so far): {result.status}',
                throttle_duration_sec=1.0)
        if not result.corrected:
            self.get_logger().debug(f'pose passed through: {result.status}')
        self.pose_pub.publish(PoseStamped(header=header, pose=matrix_to_pose(result.T_moving)))
        # the per-frame extras are built only while someone listens
        if self.state_pub.get_subscription_count() > 0:
            state = contact_state_msg(
                result, Header(stamp=header.stamp, frame_id=self._fixed_frame()),
                self.get_parameter('moving_object').value,
                self.get_parameter('fixed_object').value)
            state.status = f'{state.status}; {self._summary()}'
            self.state_pub.publish(state)
        self.track.append((stamp, result.T_moving))      # bounded (track_length)
        if self.track_pub.get_subscription_count() > 0:
            stamps = [s for s, _ in self.track]
            self.track_pub.publish(matrices_to_path(np.array([M for _, M in self.track]),
                                                    frame, stamps))
        self._smooth(T, self.fixed_T, header, result)

    # --- service --------------------------------------------------------------------------

    def _on_service(self, request: CorrectTrajectory.Request,
                    response: CorrectTrajectory.Response) -> CorrectTrajectory.Response:
        try:
            moving, fixed = self._request_models(request)
            T_m, stamps = path_to_matrices(request.moving_track)
            T_f, _ = path_to_matrices(request.fixed_track)
            if len(T_f) == 1:
                T_f = np.repeat(T_f, len(T_m), axis=0)
            elif len(T_f) != len(T_m):
                raise ValueError(f'fixed_track has {len(T_f)} poses; give 1 or '
                                 f'{len(T_m)} (one per moving pose)')
            opts = self._options()
            opts['optimal'] = bool(request.optimal)
            if request.tolerance > 0:
                opts['tolerance'] = float(request.tolerance)
            elif request.tolerance < 0:
                raise ValueError(f'tolerance must be >= 0, got {request.tolerance}')
        except (ValueError, FileNotFoundError, OSError) as exc:
            response.success = False
            response.message = str(exc)
            self.get_logger().warning(f'correct_trajectory request failed: {exc}')
            return response
        frame = request.moving_track.header.frame_id or (
            request.moving_track.poses[0].header.frame_id if request.moving_track.poses else '')
        out = []
        try:
            relation = self._relation()
            results = correct_trajectory(
                moving, fixed, T_m, T_f,
                relations=[relation] * len(T_m) if relation is not None else None,
                recognition=self._recognition(), **opts)
        except ValueError as exc:
            response.success = False
            response.message = str(exc)
            return response
        for k, r in enumerate(results):
            out.append(r.T_moving)
            response.states.append(contact_state_msg(
                r, Header(stamp=ns_to_stamp(int(stamps[k])), frame_id=self._fixed_frame()),
                request.moving_object or self.get_parameter('moving_object').value,
                request.fixed_object or self.get_parameter('fixed_object').value))
        response.corrected_track = matrices_to_path(np.array(out).reshape(-1, 4, 4), frame,
                                                    stamps)
        n_ok = sum(s.corrected for s in response.states)
        response.success = True
        response.message = f'{n_ok} of {len(out)} frames corrected'
        return response

    def _request_models(self, request: CorrectTrajectory.Request
                        ) -> Tuple[Polyhedron, Polyhedron]:
        g = self.get_parameter
        names = (request.moving_object or g('moving_object').value,
                 request.fixed_object or g('fixed_object').value)
        if names == (g('moving_object').value, g('fixed_object').value):
            if self.model_error:
                raise ValueError(self.model_error)
            return self.moving, self.fixed
        return load_polyhedron(names[0]), load_polyhedron(names[1])


def main(args=None) -> None:
    """Run the node."""
    rclpy.init(args=args)
    node = create_node_or_exit(ContactCorrectionNode, 'contact_correction_node')
    spin_until_shutdown(node)
