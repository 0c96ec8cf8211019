"""``object_localizer_node``: localises and tracks known models in ``points2``.

Subscribes ``points2`` (sensor_msgs/PointCloud2, sensor-data QoS). For every model named in the
``models`` parameter publishes ``objects/<name>/pose`` (PoseStamped, the cloud's frame and
stamp), ``objects/<name>/track`` (nav_msgs/Path of the recent poses) and
``objects/<name>/cloud`` (PointCloud2: the scene points inside the model's bounding box at the
found pose, grown by ``segment_margin``; the object's own cloud for the IP modeler).
"""

from __future__ import annotations

from dataclasses import replace
import sys
from typing import Dict, List

import numpy as np
import rclpy
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor, \
    ParameterType, SetParametersResult
from geometry_msgs.msg import PoseStamped
from nav_msgs.msg import Path
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2

from object_localizer.localization import prepare_model, segment_object_points
from object_localizer.tracking import ObjectTracker, TrackerSettings
from stereo_manip_tools.conversions import matrices_to_path, matrix_to_pose, \
    read_pointcloud2, stamp_to_ns, xyz_to_pointcloud2
from stereo_manip_tools.mesh_io import find_model, load_obj
from stereo_manip_tools.transforms import make_transform, matrix_from_quaternion
from stereo_manip_tools.parameters import float_descriptor as _float, INPUT_QOS_CHOICES, \
    input_qos_descriptor, input_qos_profile, reject_nonfinite_parameters
from stereo_manip_tools.robustness import create_node_or_exit, InputRejections

__all__ = ['ObjectLocalizerNode', 'main']


class ObjectLocalizerNode(Node):
    """Thin ROS wrapper around :class:`object_localizer.tracking.ObjectTracker`."""

    def __init__(self, **kwargs) -> None:
        super().__init__('object_localizer', **kwargs)
        self.add_on_set_parameters_callback(self._on_set_parameters)
        reject_nonfinite_parameters(self)
        self.declare_parameter('models', ['peg'], ParameterDescriptor(
            type=ParameterType.PARAMETER_STRING_ARRAY, read_only=True,
            description='model names (OBJ files found by stereo_manip_tools.mesh_io.find_model)'))
        self.declare_parameter('input_qos', 'reliable', input_qos_descriptor('points2'))
        self.declare_parameter('voxel_size', 0.003, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE, read_only=True,
            description='sampling resolution of model and scene [m]',
            floating_point_range=[FloatingPointRange(from_value=0.0005, to_value=0.05)]))
        self.declare_parameter('max_correspondence_distance', 0.01,
                               _float('ICP correspondence radius [m]', 0.0005, 0.2))
        self.declare_parameter('loss_scale', 0.0015,
                               _float('Tukey M-estimator scale k [m]', 0.0002, 0.1))
        self.declare_parameter('min_inlier_fraction', 0.5,
                               _float('below it the object is searched globally / not found',
                                      0.0, 1.0))
        self.declare_parameter('segment_margin', 0.005,
                               _float('margin around the model box for objects/<name>/cloud [m]',
                                      0.0, 0.1))
        self.declare_parameter('initial_poses', Parameter.Type.DOUBLE_ARRAY, ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY, read_only=True,
            description='optional start poses in the cloud frame, 7 numbers per model in '
                        '`models` order: x y z [m] qx qy qz qw; unset = global search'))
        self.declare_parameter('max_points', 400_000, ParameterDescriptor(
            type=ParameterType.PARAMETER_INTEGER, description='larger clouds are voxel-'
            'downsampled to at most this many points (bounded work per cloud; counted)',
            integer_range=[IntegerRange(from_value=1000, to_value=5_000_000)]))
        self.declare_parameter('track_length', 300, ParameterDescriptor(
            type=ParameterType.PARAMETER_INTEGER, description='poses kept in each track',
            integer_range=[IntegerRange(from_value=1, to_value=100000)]))
        voxel = self.get_parameter('voxel_size').value
        names = list(self.get_parameter('models').value)
        initial = self.get_parameter_or('initial_poses', None).value \
            if self.has_parameter('initial_poses') else None
        if initial is not None and len(initial) != 7 * len(names):
            raise ValueError(f'initial_poses has {len(initial)} numbers; expected 7 per model '
                             f'({7 * len(names)} for {names})')
        self.trackers: Dict[str, ObjectTracker] = {}
        self.pose_pubs = {}
        self.track_pubs = {}
        self.cloud_pubs = {}
        for k, name in enumerate(names):
            mesh = load_obj(find_model(name))
            self.trackers[name] = ObjectTracker(prepare_model(mesh, voxel), self._settings())
            if initial is not None:
                x, y, z, qx, qy, qz, qw = initial[7 * k:7 * k + 7]
                self.trackers[name].reset(make_transform(
                    matrix_from_quaternion([qx, qy, qz, qw]), [x, y, z]))
            self.pose_pubs[name] = self.create_publisher(PoseStamped, f'objects/{name}/pose', 10)
            self.track_pubs[name] = self.create_publisher(Path, f'objects/{name}/track', 10)
            self.cloud_pubs[name] = self.create_publisher(PointCloud2, f'objects/{name}/cloud',
                                                          10)
        self.counts = {'received': 0, 'rejected': 0, 'not_found': 0}
        # A full-frame cloud is megabytes: best-effort DDS drops such samples whole when one
        # fragment is lost, so the default is reliable with a short queue (newest kept).
        self.rejections = InputRejections(self.get_logger())
        self.create_subscription(PointCloud2, 'points2',
                                 self.rejections.guard(self._on_cloud, 'points2'),
                                 input_qos_profile(self.get_parameter('input_qos').value))
        self.get_logger().info(f'localising {", ".join(self.trackers)} in points2')

    _SETTING_OF_PARAMETER = {'max_correspondence_distance': 'max_distance',
                             'loss_scale': 'loss_scale',
                             'min_inlier_fraction': 'min_inlier_fraction',
                             'track_length': 'max_history'}

    def _settings(self) -> TrackerSettings:
        return TrackerSettings(**{field: self.get_parameter(name).value
                                  for name, field in self._SETTING_OF_PARAMETER.items()})

    def _on_set_parameters(self, params: List[Parameter]) -> SetParametersResult:
        """The only writer of tracker settings at run time (ranges are checked by rclpy)."""
        for p in params:
            if p.name == 'input_qos' and p.value not in INPUT_QOS_CHOICES:
                return SetParametersResult(successful=False,
                                           reason=f'input_qos must be one of {INPUT_QOS_CHOICES}')
        changes = {self._SETTING_OF_PARAMETER[p.name]: p.value for p in params
                   if p.name in self._SETTING_OF_PARAMETER}
        for tracker in getattr(self, 'trackers', {}).values():
            tracker.settings = replace(tracker.settings, **changes)
        return SetParametersResult(successful=True)

    def _on_cloud(self, msg: PointCloud2) -> None:
        self.counts['received'] += 1
        try:
            reading = read_pointcloud2(msg, max_points=self.get_parameter('max_points').value,
                                       voxel_size=self.get_parameter('voxel_size').value)
        except ValueError as exc:
            self.counts['rejected'] += 1
            self.rejections.reject(getattr(exc, 'reason', 'invalid'), f'points2 rejected: {exc}')
            return
        points = reading.points
        if reading.out_of_bounds or reading.downsampled_from:
            self.rejections.reject('points_dropped_or_downsampled', f'points2: '
                                   f'{reading.out_of_bounds} out-of-bounds points dropped, '
                                   f'{reading.downsampled_from} downsampled to {len(points)}')
        stamp = stamp_to_ns(msg.header.stamp)
        for name, tracker in self.trackers.items():
            try:
                result = tracker.update(points, stamp)
            except ValueError as exc:
                self.counts['rejected'] += 1
                self.get_logger().warning(f'{name}: cloud unusable: {exc}')
                continue
            if result is None:
                self.counts['not_found'] += 1
                self.get_logger().warning(f'{name} not found (inlier fraction below threshold;'
                                          f' {self.counts["not_found"]} so far)')
                continue
            pose = PoseStamped(header=msg.header, pose=matrix_to_pose(result.pose))
            self.pose_pubs[name].publish(pose)
            segment = segment_object_points(points, tracker.model, result.pose,
                                            self.get_parameter('segment_margin').value)
            self.cloud_pubs[name].publish(xyz_to_pointcloud2(segment, msg.header))
            stamps, poses = zip(*tracker.history)
            self.track_pubs[name].publish(
                matrices_to_path(np.array(poses), msg.header.frame_id, stamps))


def main(args=None) -> None:
    """Run the node."""
    rclpy.init(args=args)
    node = None
    try:
        node = create_node_or_exit(ObjectLocalizerNode, 'object_localizer_node')
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (FileNotFoundError, ValueError) as exc:
        print(f'object_localizer_node: {exc}', file=sys.stderr)
        raise SystemExit(1)
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
