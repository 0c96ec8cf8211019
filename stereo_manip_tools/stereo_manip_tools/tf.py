"""
TF for stereo_manip nodes: broadcasters on ``/tf`` and ``/tf_static`` and a small listener.

``tf2_ros`` is not on PyPI, so this module does the part of it the nodes need, on the wire
exactly as tf2_ros does it: ``tf2_msgs/msg/TFMessage`` on ``/tf`` (reliable, volatile, depth 100:
tf2_ros ``DynamicBroadcasterQoS``) and on ``/tf_static`` (reliable, transient local, depth 1:
``StaticBroadcasterQoS``, every static transform of the node in one latched message). RViz,
``tf2_echo`` and tf2 listeners on a real ROS install read them. Where the PyPI environment lacks
``tf2_msgs`` the workspace builds a stand-in with the same name and definition
(``ros_compat/tf2_msgs``); a real install uses its own.

Frames published by stereo_manip (see the top-level README):

- ``<camera optical frame>`` -> ``<object>``: raw pose of each localised object
  (object_localizer, ``publish_tf``);
- ``<camera optical frame>`` -> ``<moving>_corrected``: contact-corrected pose
  (contact_correction);
- ``<link B frame>`` -> ``<link A frame>_corrected``: joint-corrected pose of link A
  (joint_estimator);
- ``<mount parent>`` -> ``<camera optical frame>``: static camera mount (stereo_depth_node
  parameters ``camera_mount_parent`` / ``camera_mount_pose``).

:class:`TransformListener` keeps the newest transform of every child frame and composes chains
through the tree (no interpolation in time: on a real install use tf2_ros.Buffer for that).
"""

from __future__ import annotations

from pathlib import PurePath
from typing import Callable, Dict, Iterable, List, Optional, Sequence, Tuple, Union

from geometry_msgs.msg import PoseStamped, TransformStamped
import numpy as np
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from stereo_manip_tools.conversions import matrix_to_transform, \
    pose_stamped_to_transform_stamped, transform_stamped_to_matrix
from stereo_manip_tools.parameters import bool_descriptor, string_descriptor
from stereo_manip_tools.transforms import invert_transform, pose_from_xyz_quaternion
from tf2_msgs.msg import TFMessage

__all__ = [
    'TF_TOPIC',
    'TF_STATIC_TOPIC',
    'DYNAMIC_BROADCASTER_QOS',
    'DYNAMIC_LISTENER_QOS',
    'STATIC_BROADCASTER_QOS',
    'TransformBroadcaster',
    'StaticTransformBroadcaster',
    'PoseTfPublisher',
    'object_frame',
    'publish_camera_mount',
    'TransformListener',
    'FrameLookupError',
]

TF_TOPIC = '/tf'
TF_STATIC_TOPIC = '/tf_static'

#: tf2_ros.DynamicBroadcasterQoS
DYNAMIC_BROADCASTER_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                                     reliability=ReliabilityPolicy.RELIABLE,
                                     durability=DurabilityPolicy.VOLATILE)
#: tf2_ros.StaticBroadcasterQoS (a late subscriber still gets the static transforms)
STATIC_BROADCASTER_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST,
                                    reliability=ReliabilityPolicy.RELIABLE,
                                    durability=DurabilityPolicy.TRANSIENT_LOCAL)
#: what tf2_ros listeners subscribe /tf with
DYNAMIC_LISTENER_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                                  reliability=ReliabilityPolicy.RELIABLE,
                                  durability=DurabilityPolicy.VOLATILE)

TransformLike = Union[TransformStamped, Iterable[TransformStamped]]


def _as_list(transforms: TransformLike) -> List[TransformStamped]:
    if isinstance(transforms, TransformStamped):
        return [transforms]
    out = list(transforms)
    for t in out:
        if not isinstance(t, TransformStamped):
            raise TypeError(f'expected geometry_msgs/TransformStamped, got {type(t).__name__}')
    return out


def _check(t: TransformStamped) -> None:
    if not t.header.frame_id or not t.child_frame_id:
        raise ValueError('a transform needs both header.frame_id and child_frame_id '
                         f'(got {t.header.frame_id!r} -> {t.child_frame_id!r})')
    if t.header.frame_id == t.child_frame_id:
        raise ValueError(f'transform from frame {t.child_frame_id!r} to itself')


class TransformBroadcaster:
    """``tf2_ros.TransformBroadcaster``: publishes transforms on ``/tf``."""

    def __init__(self, node: Node, qos: QoSProfile = DYNAMIC_BROADCASTER_QOS) -> None:
        self._pub = node.create_publisher(TFMessage, TF_TOPIC, qos)

    def send_transform(self, transforms: TransformLike) -> None:
        """
        Publish one transform or several in one ``TFMessage``.

        :raises ValueError: a transform without parent or child frame, or from a frame to itself.
        """
        items = _as_list(transforms)
        for t in items:
            _check(t)
        self._pub.publish(TFMessage(transforms=items))


class StaticTransformBroadcaster:
    """
    ``tf2_ros.StaticTransformBroadcaster``: latched transforms on ``/tf_static``.

    Every call publishes all static transforms sent so far (one per child frame, the newest
    wins), as tf2_ros does: ``/tf_static`` keeps only the last message per publisher.
    """

    def __init__(self, node: Node, qos: QoSProfile = STATIC_BROADCASTER_QOS) -> None:
        self._pub = node.create_publisher(TFMessage, TF_STATIC_TOPIC, qos)
        self._by_child: Dict[str, TransformStamped] = {}

    def send_transform(self, transforms: TransformLike) -> None:
        """Add (or replace, by child frame) static transforms and publish them all."""
        for t in _as_list(transforms):
            _check(t)
            self._by_child[t.child_frame_id] = t
        self._pub.publish(TFMessage(transforms=list(self._by_child.values())))


class PoseTfPublisher:
    """
    The TF hook of a node that publishes object poses.

    Declares the parameter ``publish_tf`` (bool, default true; read at every call, so it can be
    switched at run time) and broadcasts a ``PoseStamped`` as the transform
    ``pose.header.frame_id -> child_frame``. A pose that cannot be a transform (empty frame, NaN)
    is counted in :attr:`errors` and skipped, never raised into the node's callback.
    """

    def __init__(self, node: Node, default: bool = True) -> None:
        self._node = node
        node.declare_parameter('publish_tf', default, bool_descriptor(
            'broadcast the published object poses on /tf (tf2_msgs/TFMessage)'))
        self._broadcaster: Optional[TransformBroadcaster] = None
        self.sent = 0
        self.errors = 0

    @property
    def enabled(self) -> bool:
        """Return the current value of ``publish_tf``."""
        return bool(self._node.get_parameter('publish_tf').value)

    def send(self, poses: Sequence[Tuple[PoseStamped, str]]) -> None:
        """Broadcast ``[(pose, child_frame), ...]`` in one TFMessage (if ``publish_tf``)."""
        if not poses or not self.enabled:
            return
        transforms = []
        for pose, child in poses:
            try:
                t = pose_stamped_to_transform_stamped(pose, child)
                _check(t)
            except ValueError as exc:
                self.errors += 1
                self._node.get_logger().warning(
                    f'pose not broadcast on /tf as {child!r} ({self.errors} so far): {exc}')
                continue
            transforms.append(t)
        if transforms:
            if self._broadcaster is None:
                self._broadcaster = TransformBroadcaster(self._node)
            self._broadcaster.send_transform(transforms)
            self.sent += len(transforms)

    def follow(self, publisher: Publisher, child_frame: Union[str, Callable[[], str]]) -> None:
        """
        Broadcast every PoseStamped ``publisher`` publishes, as ``child_frame``.

        Broadcast every PoseStamped ``publisher`` publishes, as ``child_frame`` (a name or a
        function giving it at publish time), right after the pose itself is published.
        """
        publish = publisher.publish

        def publish_and_broadcast(msg: PoseStamped) -> None:
            publish(msg)
            self.send_pose(msg, child_frame() if callable(child_frame) else child_frame)
        publisher.publish = publish_and_broadcast

    def send_pose(self, pose: PoseStamped, child_frame: str) -> None:
        """Broadcast one pose as ``pose.header.frame_id -> child_frame``."""
        self.send([(pose, child_frame)])


def object_frame(model: str) -> str:
    """TF frame name of an object given by model name or mesh path (``/x/peg.obj`` -> ``peg``)."""
    return PurePath(model).stem if ('/' in model or '.' in model) else model


#: the optical frame of a camera body frame (x forward, z up) rotated to z forward, x right,
#: y down (REP 103): the quaternion a mount transform ends with for a camera looking along +x
BODY_TO_OPTICAL_QUATERNION = (-0.5, 0.5, -0.5, 0.5)


def publish_camera_mount(node: Node) -> Optional[StaticTransformBroadcaster]:
    """
    Declare the camera-mount parameters and publish the static transform they describe.

    Parameters (read-only): ``camera_mount_parent`` (frame the camera is mounted on, e.g.
    ``base_link`` or ``world``; empty, the default: no transform is published),
    ``camera_frame`` (the camera's optical frame, the ``frame_id`` of its images; default
    ``stereo_left_optical``), ``camera_mount_pose`` (``[x y z qx qy qz qw]`` of the optical frame
    in the parent frame [m]; a camera looking along the parent's +x with no tilt has the
    quaternion ``BODY_TO_OPTICAL_QUATERNION``).

    :returns: the broadcaster (kept alive by the caller), or None when no parent is set or the
        parameters are malformed (logged as an error naming what is wrong).
    """
    parent = node.declare_parameter('camera_mount_parent', '', string_descriptor(
        'frame the camera is mounted on (static TF parent -> camera_frame); empty: no mount '
        'transform', read_only=True)).value
    child = node.declare_parameter('camera_frame', 'stereo_left_optical', string_descriptor(
        "the camera's optical frame (frame_id of its images), child of the mount transform",
        read_only=True)).value
    values = node.declare_parameter(
        'camera_mount_pose', [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], ParameterDescriptor(
            type=ParameterType.PARAMETER_DOUBLE_ARRAY, read_only=True,
            description='[x y z qx qy qz qw] of camera_frame in camera_mount_parent [m]')).value
    if not parent:
        return None
    try:
        T = pose_from_xyz_quaternion(values, 'camera_mount_pose')
        if parent == child:
            raise ValueError(f'camera_mount_parent equals camera_frame ({child!r})')
    except ValueError as exc:
        node.get_logger().error(f'no camera mount transform published: {exc}')
        return None
    t = TransformStamped(child_frame_id=child, transform=matrix_to_transform(T))
    t.header.frame_id = parent
    t.header.stamp = node.get_clock().now().to_msg()
    broadcaster = StaticTransformBroadcaster(node)
    broadcaster.send_transform(t)
    node.get_logger().info(f'static camera mount {parent} -> {child} on /tf_static')
    return broadcaster


class FrameLookupError(KeyError):
    """No chain of transforms connects the two frames."""


class TransformListener:
    """
    Newest transform per child frame from ``/tf`` and ``/tf_static``; chains composed.

    A minimal stand-in for ``tf2_ros.Buffer`` + ``TransformListener`` (no time interpolation,
    no extrapolation checks): enough for a controller that needs the newest pose of a frame in
    another frame, and for tests.
    """

    def __init__(self, node: Node) -> None:
        # child -> (parent, T_parent_child, stamp_ns, static)
        self.edges: Dict[str, Tuple[str, np.ndarray, int, bool]] = {}
        self.received = 0
        self.rejected = 0
        node.create_subscription(TFMessage, TF_TOPIC, lambda m: self._on_tf(m, False),
                                 DYNAMIC_LISTENER_QOS)
        node.create_subscription(TFMessage, TF_STATIC_TOPIC, lambda m: self._on_tf(m, True),
                                 STATIC_BROADCASTER_QOS)

    def _on_tf(self, msg: TFMessage, static: bool) -> None:
        for t in msg.transforms:
            self.received += 1
            try:
                T, stamp, parent, child = transform_stamped_to_matrix(t)
                _check(t)
            except ValueError:
                self.rejected += 1
                continue
            self.edges[child] = (parent, T, stamp, static)

    def frames(self) -> List[str]:
        """Every frame seen, parents and children."""
        return sorted(set(self.edges) | {e[0] for e in self.edges.values()})

    def _chain_to_root(self, frame: str) -> List[str]:
        chain = [frame]
        while chain[-1] in self.edges:
            parent = self.edges[chain[-1]][0]
            if parent in chain:     # a loop: stop (tf2 would reject the second edge)
                break
            chain.append(parent)
        return chain

    def _to_ancestor(self, frame: str, ancestor: str) -> Tuple[np.ndarray, int]:
        """``T_ancestor_frame`` and the oldest stamp on the way."""
        T = np.eye(4)
        stamp = None
        while frame != ancestor:
            parent, T_pc, s, static = self.edges[frame]
            T = T_pc @ T
            if not static:
                stamp = s if stamp is None else min(stamp, s)
            frame = parent
        return T, (0 if stamp is None else stamp)

    def lookup(self, target_frame: str, source_frame: str) -> Tuple[np.ndarray, int]:
        """
        Newest ``T_target_source`` (maps points of ``source_frame`` into ``target_frame``).

        :returns: ``(T 4x4, stamp_ns)`` where the stamp is the oldest dynamic stamp in the chain
            (0 if only static transforms are involved).
        :raises FrameLookupError: the frames are not connected.
        """
        if target_frame == source_frame:
            return np.eye(4), 0
        up_source = self._chain_to_root(source_frame)
        up_target = self._chain_to_root(target_frame)
        common = next((f for f in up_source if f in set(up_target)), None)
        if common is None:
            known = ', '.join(self.frames())
            raise FrameLookupError(f'{source_frame!r} and {target_frame!r} are not connected in '
                                   f'the TF tree (frames: {known})')
        T_c_s, s1 = self._to_ancestor(source_frame, common)
        T_c_t, s2 = self._to_ancestor(target_frame, common)
        stamps = [s for s in (s1, s2) if s]
        return invert_transform(T_c_t) @ T_c_s, (min(stamps) if stamps else 0)

    def can_transform(self, target_frame: str, source_frame: str) -> bool:
        """Whether :meth:`lookup` would succeed."""
        try:
            self.lookup(target_frame, source_frame)
        except FrameLookupError:
            return False
        return True

    def stamp_of(self, child_frame: str) -> Optional[int]:
        """Stamp [ns] of the newest transform of ``child_frame`` (None: never received)."""
        e = self.edges.get(child_frame)
        return None if e is None else e[2]
