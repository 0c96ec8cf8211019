"""
``object_localizer_node``: finds, tracks and verifies known models in ``points2``.

Subscribes ``points2`` (sensor_msgs/PointCloud2; organised or not; QoS from ``input_qos``). A
worker thread always processes the newest cloud (older unprocessed clouds are dropped and
counted), so the node keeps up with a free-running camera. For every model in ``models``:

- ``objects/<name>/status`` (stereo_manip_msgs/TrackStatus): state, quality, inlier fraction,
  visible-surface residual, prediction error and reason, for EVERY processed cloud;
- ``objects/<name>/pose`` (PoseStamped, the cloud's frame and stamp): only poses that passed
  the quality check (see ``object_localizer/README.md``);
- ``objects/<name>/track`` (nav_msgs/Path of the last ``track_length`` verified poses) and
  ``objects/<name>/cloud`` (PointCloud2: the scene points inside the model's box at the pose,
  grown by ``segment_margin``): built only while someone subscribes.
"""

from __future__ import annotations

from dataclasses import replace
import threading
import time
from typing import Dict, List, Optional

from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
import numpy as np
from object_localizer import lean_open3d  # noqa: F401 (before Open3D is imported)
from object_localizer.acquisition import prepare_acquisition_model
from object_localizer.conversions import camera_from_camera_info, cloud_xyz, track_status
from object_localizer.naming import identical_groups, name_identical_parts
from object_localizer.tracking import make_acquirer, ObjectTracker, prepare_tracking_model, \
    same_shape, SceneCloud, TrackerSettings, TrackState, TrackUpdate, withdraw_overlapping
from object_localizer.verification import PinholeCamera
from rcl_interfaces.msg import FloatingPointRange, ParameterDescriptor, ParameterType, \
    SetParametersResult
import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, PointCloud2
from stereo_manip_msgs.msg import TrackStatus
from stereo_manip_tools.conversions import matrices_to_path, matrix_to_pose, stamp_to_ns, \
    xyz_to_pointcloud2
from stereo_manip_tools.diagnostics import NodeDiagnostics
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.parameters import float_descriptor as _float, INPUT_QOS_CHOICES, \
    input_qos_descriptor, input_qos_profile, int_descriptor, reject_nonfinite_parameters, \
    string_descriptor
from stereo_manip_tools.processes import process_age_seconds
from stereo_manip_tools.robustness import create_node_or_exit, InputRejections, \
    spin_until_shutdown
from stereo_manip_tools.tf import PoseTfPublisher
from stereo_manip_tools.transforms import pose_from_xyz_quaternion
from stereo_manip_tools.worker import NewestOnlyWorker

__all__ = ['ObjectLocalizerNode', 'main']


class ObjectLocalizerNode(Node):
    """Thin ROS wrapper around :class:`object_localizer.tracking.ObjectTracker`."""

    #: node parameter -> TrackerSettings field (all may be changed at run time)
    _SETTING_OF_PARAMETER = {
        'max_correspondence_distance': 'max_distance',
        'loss_scale': 'loss_scale',
        'inlier_distance': 'inlier_distance',
        'min_inlier_fraction': 'min_inlier_fraction',
        'min_acquisition_inlier_fraction': 'min_acquisition_inlier_fraction',
        'max_visible_residual': 'max_visible_residual',
        'max_free_space_fraction': 'max_free_space_fraction',
        'max_prediction_error': 'max_prediction_error',
        'min_edge_fraction': 'min_edge_fraction',
        'max_penetration': 'max_penetration',
        'explained_radius': 'explained_radius',
        'stereo_baseline': 'stereo_baseline',
        'static_recheck_period': 'static_recheck_period',
        'static_average': 'static_average',
        'static_average_gate': 'static_average_gate',
        'relock_window': 'relock_window',
        'relock_shift': 'relock_shift',
        'relock_turn': 'relock_turn',
        'slide_min_step': 'slide_min_step',
        'min_support_ratio': 'min_support_ratio',
        'twin_max_speed': 'twin_max_speed',
        'motion_memory': 'motion_memory',
        'track_length': 'max_history',
    }

    def __init__(self, **kwargs) -> None:
        # start-up time line [s of time.monotonic()]: logged once with the first pose
        now = time.monotonic()
        self._startup = {'process start': now - process_age_seconds(), 'node': now}
        super().__init__('object_localizer', **kwargs)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        reject_nonfinite_parameters(self)
        self.rejections = InputRejections(self.get_logger())
        self.declare_parameter('models', ['peg'], ParameterDescriptor(
            type=ParameterType.PARAMETER_STRING_ARRAY, read_only=True,
            description='model names (OBJ files found by stereo_manip_tools.mesh_io.find_model)'))
        self.declare_parameter('static_objects', Parameter.Type.STRING_ARRAY, ParameterDescriptor(
            type=ParameterType.PARAMETER_STRING_ARRAY, read_only=True,
            description='names of `models` that do not move: localised once, then held and '
                        're-verified every static_recheck_period s'))
        self.declare_parameter('input_qos', 'reliable', input_qos_descriptor('points2'))
        self.declare_parameter('acquisition_method', 'ppf', string_descriptor(
            'global acquisition: ppf (point-pair-feature voting), fpfh (FPFH + RANSAC), both '
            'with visibility verification (object_localizer.acquisition), or rough_fine (the '
            'FPFH + RANSAC + ICP of object_localizer.localization)', read_only=True,
            additional_constraints='one of ppf, fpfh, rough_fine'))
        self.declare_parameter('voxel_size', 0.003, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE, read_only=True,
            description='sampling resolution of the acquisition templates [m]',
            floating_point_range=[FloatingPointRange(from_value=0.0005, to_value=0.05)]))
        self.declare_parameter('max_correspondence_distance', 0.01,
                               _float('ICP correspondence radius [m] (twice that at first)',
                                      0.0005, 0.2))
        self.declare_parameter('loss_scale', 0.0015,
                               _float('Tukey M-estimator scale k [m]', 0.0002, 0.1))
        self.declare_parameter('inlier_distance', 0.003,
                               _float('largest surface distance [m] of an observed point for a '
                                      'model sample to count as seen', 0.0005, 0.05))
        self.declare_parameter('min_inlier_fraction', 0.75,
                               _float('smallest share of the expected-visible model surface '
                                      'seen, for a tracked pose to be published', 0.0, 1.0))
        self.declare_parameter('min_acquisition_inlier_fraction', 0.85,
                               _float('the same for an acquired pose or a hint (no prediction '
                                      'to compare with)', 0.0, 1.0))
        self.declare_parameter('max_visible_residual', 0.0015,
                               _float('largest RMS surface residual [m] of a published pose',
                                      0.0001, 0.05))
        self.declare_parameter('max_free_space_fraction', 0.15,
                               _float('largest share of the expected-visible surface the '
                                      'sensor sees through, for a published pose', 0.0, 1.0))
        self.declare_parameter('max_prediction_error', 0.02,
                               _float('largest mean displacement [m] from the constant-velocity '
                                      'prediction, for a published pose', 0.0005, 1.0))
        self.declare_parameter('min_edge_fraction', 0.25,
                               _float('smallest share of the model outline where the observed '
                                      'depth just outside jumps behind the model (a pose sunk '
                                      'into a larger surface has none), for a published pose',
                                      0.0, 1.0))
        self.declare_parameter('stereo_baseline', 0.1,
                               _float('x [m] of the second stereo camera in the cloud frame: '
                                      'the check expects only surfaces both cameras face (0: '
                                      'one viewpoint, e.g. a depth camera)', 0.0, 2.0))
        self.declare_parameter('max_penetration', 0.005,
                               _float('a pose deeper than this [m] inside another verified '
                                      'object (10 % of its volume) is rejected', 0.0005, 0.1))
        self.declare_parameter('explained_radius', 0.005,
                               _float('the global search leaves out the scene points within '
                                      'this [m] of identical parts verified in the same cloud '
                                      '(0: off)', 0.0, 0.05))
        self.declare_parameter('static_recheck_period', 1.0,
                               _float('re-verification period of static objects [s of cloud '
                                      'stamps]', 0.0, 3600.0))
        self.declare_parameter('static_average', 30,
                               int_descriptor('a static object is held at the mean of its last '
                                              'this many poses refined and verified at its '
                                              're-checks (1: the first verified pose is held)',
                                              1, 1000))
        self.declare_parameter('static_average_gate', 0.003,
                               _float('a re-check pose farther than this [m, mean displacement] '
                                      'from the static mean restarts it (the object moved)',
                                      0.0001, 0.1))
        self.declare_parameter('relock_window', 1.0,
                               _float('after a loss, for this long [s of cloud stamps] the lost '
                                      'track is re-acquired locally first (0: off)',
                                      0.0, 60.0))
        self.declare_parameter('relock_shift', 0.012,
                               _float('local re-acquisition also starts the ICP shifted by '
                                      '+- this [m] along each model axis', 0.0, 0.1))
        self.declare_parameter('relock_turn', 0.15,
                               _float('... and turned by +- this [rad] about each model axis',
                                      0.0, 1.0))
        self.declare_parameter('slide_min_step', 0.004,
                               _float('a pose found without a motion prediction is searched '
                                      'along the model axes for better scene support, in steps '
                                      'halved down to this [m] (0: off)', 0.0, 0.05))
        self.declare_parameter('min_support_ratio', 1.25,
                               _float('of overlapping places that pass the acquisition check, '
                                      'one supported by this many times the scene samples of '
                                      'every other is taken (0: such places stay ambiguous)',
                                      0.0, 100.0))
        self.declare_parameter('twin_max_speed', 0.1,
                               _float('identical parts: the radius within which a place may '
                                      'carry the name of a part grows by this [m/s] with the '
                                      'age of its last verified pose', 0.0, 10.0))
        self.declare_parameter('motion_memory', 2.0,
                               _float('a track re-acquired within this long [s of cloud stamps] '
                                      'of its last verified pose keeps its velocity from before '
                                      'the loss (0: starts without one)', 0.0, 60.0))
        self.declare_parameter('search_cpu_share', 0.5,
                               _float('while a moving (not static) object tracks, global '
                                      'searches run only while '
                                      'their CPU stays below this share of the wall time (a '
                                      'credit, at most search_cpu_burst): the tracked objects '
                                      'keep the camera rate; the others are searched in later '
                                      'clouds (status reason "global search deferred"); 1: '
                                      'no cap', 0.05, 1.0))
        self.declare_parameter('search_cpu_burst', 1.0,
                               _float('largest search CPU credit [s] saved up while no search '
                                      'runs', 0.1, 60.0))
        self.declare_parameter('publish_uncertain_naming', False, ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description='identical parts left ambiguous by stale known poses are named by the '
                        'assignment nearest those poses also when it is not decisive (cost not '
                        'below half the next one): the poses are published with the status '
                        'state ACQUIRING and the reason "naming uncertain" (the parts may be '
                        'swapped); false (default): such parts get no pose'))
        self.declare_parameter('segment_margin', 0.005,
                               _float('margin around the model box for objects/<name>/cloud [m]',
                                      0.0, 0.1))
        self.declare_parameter('initial_poses', Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY, read_only=True,
            description='optional hints of the start poses in the cloud frame, 7 numbers per '
                        'model in `models` order: x y z [m] qx qy qz qw; verified like any pose '
                        '(global search when they do not fit); unset = global search'))
        self.declare_parameter('max_points', 100_000, int_descriptor(
            'clouds with more valid points are voxel-downsampled to at most this many '
            '(bounded work per cloud)', 1000, 5_000_000))
        self.declare_parameter('track_length', 300, int_descriptor(
            'verified poses kept per object for objects/<name>/track', 2, 100000))
        voxel = self.get_parameter('voxel_size').value
        names = list(self.get_parameter('models').value)
        static_param = self.get_parameter_or('static_objects', None)
        static = [s for s in (static_param.value or []) if s] if static_param is not None else []
        unknown = sorted(set(static) - set(names))
        if unknown:
            raise ValueError(f'static_objects {unknown} are not in models {names}')
        initial = self.get_parameter_or('initial_poses', None).value \
            if self.has_parameter('initial_poses') else None
        if initial is not None and len(initial) != 7 * len(names):
            raise ValueError(f'initial_poses has {len(initial)} numbers; expected 7 per model '
                             f'({7 * len(names)} for {names})')
        # the global search's visibility score models the stereo camera: intrinsics from the
        # left CameraInfo of the cloud's frame (a virtual camera until one arrives), baseline
        # from stereo_baseline (the check's)
        self._camera: Optional[PinholeCamera] = None
        self._camera_frame = ''      # frame of the CameraInfo that gave _camera
        self._cloud_frame = ''
        acquirer = make_acquirer(self.get_parameter('acquisition_method').value,
                                 camera=self._acquisition_camera,
                                 stereo_baseline=lambda: self.get_parameter(
                                     'stereo_baseline').value)
        self._startup['parameters'] = time.monotonic()
        self.trackers: Dict[str, ObjectTracker] = {}
        self.pose_pubs, self.status_pubs, self.track_pubs, self.cloud_pubs = {}, {}, {}, {}
        for k, name in enumerate(names):
            model = prepare_tracking_model(load_obj(find_model(name)), voxel)
            if self.get_parameter('acquisition_method').value != 'rough_fine':
                model.acquisition = prepare_acquisition_model(model.mesh)
            tracker = ObjectTracker(model, replace(self._settings(), static=name in static),
                                    acquirer=acquirer)
            if initial is not None:
                tracker.reset(pose_from_xyz_quaternion(initial[7 * k:7 * k + 7],
                                                       f'initial_poses of {name}'))
            self.trackers[name] = tracker
            self.pose_pubs[name] = self.create_publisher(PoseStamped, f'objects/{name}/pose', 10)
            self.status_pubs[name] = self.create_publisher(TrackStatus,
                                                           f'objects/{name}/status', 10)
            self.track_pubs[name] = self.create_publisher(Path, f'objects/{name}/track', 10)
            self.cloud_pubs[name] = self.create_publisher(PointCloud2, f'objects/{name}/cloud',
                                                          10)
        self._startup['models'] = time.monotonic()
        for name, tracker in self.trackers.items():
            tracker.twins = [t for n, t in self.trackers.items()
                             if n != name and same_shape(tracker.model, t.model)]
            if tracker.twins:
                twins = ', '.join(t.model.name for t in tracker.twins)
                self.get_logger().info(
                    f'{name} has the same shape as {twins}: it is acquired only near a known '
                    'pose (initial_poses or the last one)')
        self._groups = identical_groups(self.trackers)
        # static objects first: the others are checked against their verified poses
        self._order = sorted(names, key=lambda n: n not in static)
        self.counts = {'received': 0, 'processed': 0, 'dropped_stale': 0, 'rejected': 0,
                       'published': 0, 'lost': 0, 'acquired': 0, 'searches_deferred': 0,
                       'withdrawn': 0}
        # global-search CPU credit [s] and the wall time [s, monotonic] it was last updated
        self._search_credit = self.get_parameter('search_cpu_burst').value
        self._credit_time = time.monotonic()
        self._cpu: Dict[str, List[float]] = {n: [] for n in names}
        self._lock = threading.Lock()            # the pending cloud and the counts
        self._settings_lock = threading.Lock()   # tracker settings vs. the tracker's update
        self._worker = NewestOnlyWorker(self._work, 'localizer', self._lock)
        self._worker.start()
        self.tf = PoseTfPublisher(self)   # every published pose also on /tf, child = model name
        for name, pub in self.pose_pubs.items():
            self.tf.follow(pub, name)
        self.create_subscription(PointCloud2, 'points2', self._on_cloud,
                                 input_qos_profile(self.get_parameter('input_qos').value))
        self.create_subscription(CameraInfo, 'left/camera_info', self._on_camera_info,
                                 qos_profile_sensor_data)
        self.create_timer(10.0, self._log_stats)
        self.get_logger().info(
            f'localising {", ".join(names)} in points2'
            + (f' ({", ".join(static)} static)' if static else '')
            + ('; initial poses are hints, verified before use' if initial is not None else ''))
        self.diagnostics = NodeDiagnostics(self, self.counts)  # /diagnostics: topics, counters
        self._startup['subscribed'] = time.monotonic()

    def _settings(self) -> TrackerSettings:
        return TrackerSettings(**{field: self.get_parameter(name).value
                                  for name, field in self._SETTING_OF_PARAMETER.items()})

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        """Write the tracker settings at run time (the only writer; rclpy checks the ranges)."""
        for p in params:
            if p.name == 'input_qos' and p.value not in INPUT_QOS_CHOICES:
                return SetParametersResult(successful=False,
                                           reason=f'input_qos must be one of {INPUT_QOS_CHOICES}')
            if p.type_ == Parameter.Type.DOUBLE and not np.isfinite(p.value):
                return SetParametersResult(successful=False, reason=f'{p.name} must be finite')
        changes = {self._SETTING_OF_PARAMETER[p.name]: p.value for p in params
                   if p.name in self._SETTING_OF_PARAMETER}
        if changes:
            with getattr(self, '_settings_lock', threading.Lock()):
                for tracker in getattr(self, 'trackers', {}).values():
                    tracker.settings = replace(tracker.settings, **changes)
        return SetParametersResult(successful=True)

    def _on_camera_info(self, msg: CameraInfo) -> None:
        """Keep the left camera's rectified intrinsics (P) for the acquisition's score."""
        try:
            camera = camera_from_camera_info(msg)
        except ValueError as exc:     # the last good camera (or the virtual one) stays
            self.get_logger().warning(f'left/camera_info ignored: {exc}',
                                      throttle_duration_sec=10.0)
            return
        if camera != self._camera:
            self.get_logger().info(
                f'acquisition camera from left/camera_info ({msg.header.frame_id}): {camera}; '
                f'stereo baseline {self.get_parameter("stereo_baseline").value} m '
                '(stereo_baseline)')
        self._camera = camera
        self._camera_frame = msg.header.frame_id

    def _acquisition_camera(self) -> Optional[PinholeCamera]:
        """Return the CameraInfo intrinsics if they describe the clouds' frame, else None."""
        camera, frame = self._camera, self._camera_frame
        if camera is None or (frame and self._cloud_frame and frame != self._cloud_frame):
            return None
        return camera

    def _on_cloud(self, msg: PointCloud2) -> None:
        self._startup.setdefault('first cloud', time.monotonic())
        self._cloud_frame = msg.header.frame_id
        with self._lock:
            self.counts['received'] += 1
            if self._worker.put(msg):
                self.counts['dropped_stale'] += 1

    def _work(self, msg: PointCloud2) -> None:
        try:
            self._process(msg)
        except Exception as exc:  # keep the node alive; the reason is logged and counted
            if not self.context.ok():
                return              # shutting down (Ctrl-C): nothing to publish to
            self.counts['rejected'] += 1
            self.get_logger().error(f'cloud not processed: {type(exc).__name__}: {exc}')

    def _process(self, msg: PointCloud2) -> None:
        self._startup.setdefault('first cloud taken', time.monotonic())
        try:
            scene = SceneCloud(cloud_xyz(msg, self.get_parameter('max_points').value,
                                         self.get_parameter('voxel_size').value))
        except ValueError as exc:
            self.counts['rejected'] += 1
            self.rejections.reject(getattr(exc, 'reason', 'unusable_cloud'),
                                   f'points2 rejected: {exc}')
            return
        self.counts['processed'] += 1
        stamp = stamp_to_ns(msg.header.stamp)
        verified: list = []
        # Objects that track first (static ones first of all), published at once; a track
        # lost here and the objects without a pose are searched for afterwards: a global
        # search (0.5-4 s) never delays a tracked pose of this cloud, and sees every object
        # verified in it (a twin verified here no longer makes the search ambiguous).
        tracking = [n for n in self._order
                    if self.trackers[n].state in (TrackState.TRACKING, TrackState.STATIC)
                    and self.trackers[n].history]
        searching = [n for n in self._order if n not in tracking]
        lost: Dict[str, TrackUpdate] = {}
        for name in tracking:
            was = self.trackers[name].state
            with self._settings_lock:
                result = self.trackers[name].update(scene, stamp, verified, reacquire=False)
            if was == TrackState.TRACKING and result.lost and result.pose is None:
                lost[name] = result      # searched for below, in this cloud
                continue
            if result.pose is not None:
                verified.append((self.trackers[name].model, result.pose))
            self._publish(name, result, msg, scene)
        tracked = list(verified)
        # identical parts left unnamed by their own searches (every place they found is far
        # from their stale known poses) are named together after the others
        in_group = {n for g in self._groups for n in g}
        deferred: Dict[str, TrackUpdate] = {}
        found: Dict[str, TrackUpdate] = {}       # the searches' outcomes, in search order
        # only a moving object tracked in this cloud has a camera rate to keep: a static one is
        # held (re-checked once per static_recheck_period), so it does not defer the searches
        # (after a restart of the peg graph, the hole block found first made the peg's searches
        # wait for the credit)
        allowed = self._search_allowed(any(
            self.trackers[n].state == TrackState.TRACKING for n in tracking if n not in lost))
        for name in searching + [n for n in self._order if n in lost]:
            with self._settings_lock:
                result = self.trackers[name].update(scene, stamp, verified, search=allowed)
            self._search_credit -= result.cpu_seconds
            if 'global search deferred' in result.reason:
                self.counts['searches_deferred'] += 1
            if name in lost:     # lost in this cloud: report the loss with the search
                first = lost[name]
                result.lost = True
                result.reason = f'{first.reason}; {result.reason}'
                result.cpu_seconds += first.cpu_seconds
                if result.quality is None:
                    result.quality = first.quality
            if name in in_group and result.pose is None and self.trackers[name].places:
                deferred[name] = result
                continue
            found[name] = result
            if result.pose is not None:     # the later searches are checked against it
                verified.append((self.trackers[name].model, result.pose))
        # each search was checked against the poses before it only: a pose that overlaps a
        # better one found in this cloud (or a tracked one) is withdrawn before anything of
        # the searches is published
        for name, result in zip(found, withdraw_overlapping(
                [(self.trackers[n], r) for n, r in found.items()], tracked)):
            if result.pose is None and found[name].pose is not None:
                self.counts['withdrawn'] += 1
                if not result.lost:         # (a loss is logged with its outcome)
                    self.get_logger().warning(f'{name}: {result.reason}')
            found[name] = result
            self._publish(name, result, msg, scene)
        for group in self._groups:
            if all(n in deferred for n in group):
                t0 = time.process_time()
                with self._settings_lock:
                    named = name_identical_parts(
                        [self.trackers[n] for n in group], stamp,
                        self.get_parameter('publish_uncertain_naming').value)
                for k, result in named.items():
                    first = deferred[group[k]]
                    result.cpu_seconds = first.cpu_seconds + \
                        (time.process_time() - t0) / len(named)
                    result.reason = f'{first.reason}; then {result.reason}'
                    result.lost = first.lost
                    deferred[group[k]] = result
        for name in [n for n in self._order if n in deferred]:
            self._publish(name, deferred[name], msg, scene)

    def _search_allowed(self, tracking: bool) -> bool:
        """
        Return whether global searches may run in this cloud (``search_cpu_share``).

        ``tracking``: a moving (not static) object was tracked in this cloud.

        The credit grows by the share of the wall time since the last cloud (at most
        ``search_cpu_burst``) and every search or re-acquisition spends its CPU: with objects
        tracked in this cloud, the searches run only while the credit is positive, so they
        take at most that share of the CPU over time and the tracked objects keep the camera
        rate. With nothing tracked there is no rate to keep: they always run. Decided once per
        cloud, for all lost objects together (identical parts are named together).
        """
        now = time.monotonic()
        share = self.get_parameter('search_cpu_share').value
        self._search_credit = min(self._search_credit + share * (now - self._credit_time),
                                  self.get_parameter('search_cpu_burst').value)
        self._credit_time = now
        return not tracking or share >= 1.0 or self._search_credit > 0.0

    def _publish(self, name: str, result: TrackUpdate, msg: PointCloud2,
                 scene: SceneCloud) -> None:
        """Count, log and publish one object's outcome of a cloud."""
        tracker = self.trackers[name]
        self._cpu[name].append(result.cpu_seconds)
        if 'first pose' not in self._startup:
            self._startup.setdefault(f'{name} first outcome', time.monotonic())
        if result.lost:
            self.counts['lost'] += 1
            self.get_logger().warning(f'{name}: {result.reason}')
        if result.acquired:
            self.counts['acquired'] += 1
            self.get_logger().info(f'{name}: acquired (quality '
                                   f'{result.quality.quality:.2f}, '
                                   f'{result.cpu_seconds:.2f} s CPU)')
        if result.pose is not None and 'first pose' not in self._startup:
            self._startup['first pose'] = time.monotonic()
            self._log_startup(name, result)
        if result.pose is not None:
            self.counts['published'] += 1
            self.pose_pubs[name].publish(PoseStamped(header=msg.header,
                                                     pose=matrix_to_pose(result.pose)))
        state, reason = result.state, result.reason
        if tracker.naming_uncertain and result.pose is not None:
            # the pose is verified, its name is not: flagged (not TRACKING) on every cloud
            state = TrackState.ACQUIRING
            reason = f'naming uncertain (identical parts named by stale known poses): {reason}'
        self.status_pubs[name].publish(track_status(msg.header, name, state, result.quality,
                                                    reason, result.cpu_seconds))
        if result.pose is None:
            return
        if self.cloud_pubs[name].get_subscription_count() > 0:
            segment = scene.in_box(result.pose, tracker.model.template.points,
                                   self.get_parameter('segment_margin').value)
            self.cloud_pubs[name].publish(xyz_to_pointcloud2(segment, msg.header))
        if self.track_pubs[name].get_subscription_count() > 0 and tracker.history:
            stamps, poses = zip(*tracker.history)
            self.track_pubs[name].publish(
                matrices_to_path(np.array(poses), msg.header.frame_id, stamps))

    def _log_startup(self, name: str, result: TrackUpdate) -> None:
        """Log the start-up time line once, with the first verified pose (INFO)."""
        marks = sorted(self._startup.items(), key=lambda kv: kv[1])
        t0 = self._startup['process start']
        steps = ', '.join(f'{what} {t - t0:.2f}' for what, t in marks[1:])
        self.get_logger().info(
            f'start-up [s from process start]: {steps} ({name}: {result.reason}, '
            f'{result.cpu_seconds:.2f} s CPU; cloud {self.counts["processed"]} processed of '
            f'{self.counts["received"]} received; process CPU {time.process_time():.2f} s)')

    def _log_stats(self) -> None:
        parts = []
        for name, cpu in self._cpu.items():
            if cpu:
                ms = 1e3 * np.array(cpu)
                parts.append(f'{name} {self.trackers[name].state.name} CPU ms/cloud median '
                             f'{np.median(ms):.1f} p95 {np.percentile(ms, 95):.1f} max '
                             f'{ms.max():.1f}')
                cpu.clear()
        self.get_logger().info(f'counts {self.counts}; ' + '; '.join(parts))

    def destroy_node(self) -> None:
        self._worker.stop(timeout=10.0)
        super().destroy_node()


def main(args=None) -> None:
    """Run the node."""
    rclpy.init(args=args)
    node = create_node_or_exit(ObjectLocalizerNode, 'object_localizer_node')
    spin_until_shutdown(node)
