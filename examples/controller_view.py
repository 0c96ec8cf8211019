#!/usr/bin/env python3
"""
What a robot controller reads from stereo_manip.

The corrected object pose, the joint estimate and the TF frames.

    source scripts/env.sh
    python examples/controller_view.py --object peg --target-frame world
    python examples/controller_view.py --count 5 --json      # 5 corrected poses, JSON lines

Subscribes:
  - ``/objects/<object>/pose_corrected`` (geometry_msgs/PoseStamped, camera optical frame): the
    contact-corrected pose (the demo's remapping of contact_correction_node's corrected_pose);
  - ``/joint_estimate`` (stereo_manip_msgs/JointEstimate, link B's frame);
  - ``/tf`` and ``/tf_static``: for every corrected pose the frame ``<object>_corrected`` is
    looked up in ``--target-frame`` (e.g. ``world`` when the stereo node publishes the camera
    mount), which is what a controller plans in.

On a ROS install a controller would use ``tf2_ros.Buffer``/``TransformListener`` for the lookup;
this example uses ``stereo_manip_tools.tf.TransformListener`` (same topics, no tf2_ros on PyPI).
Only the message types and topic names tie it to stereo_manip.
"""

import argparse
import json
import sys
import time

from geometry_msgs.msg import PoseStamped
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from stereo_manip_msgs.msg import JointEstimate

from stereo_manip_tools.conversions import pose_to_matrix, stamp_to_ns
from stereo_manip_tools.tf import FrameLookupError, TransformListener
from stereo_manip_tools.transforms import quaternion_from_matrix

JOINT_TYPES = {JointEstimate.FIXED: 'fixed', JointEstimate.REVOLUTE: 'revolute',
               JointEstimate.PRISMATIC: 'prismatic', JointEstimate.SPHERICAL: 'spherical',
               JointEstimate.CYLINDRICAL: 'cylindrical', JointEstimate.PLANAR: 'planar'}


class ControllerView(Node):
    """Prints (or emits as JSON lines) what arrives; stops after ``count`` corrected poses."""

    def __init__(self, opts: argparse.Namespace) -> None:
        super().__init__('controller_view')
        self.opts = opts
        self.poses_seen = 0
        self.pending = []
        self.tf = TransformListener(self)
        self.create_subscription(PoseStamped, f'/objects/{opts.object}/pose_corrected',
                                 self.on_pose, 10)
        self.create_subscription(JointEstimate, opts.joint_topic, self.on_joint, 10)

    def emit(self, record: dict) -> None:
        if self.opts.json:
            print(json.dumps(record), flush=True)
        else:
            print('  '.join(f'{k}={v}' for k, v in record.items()), flush=True)

    def on_pose(self, msg: PoseStamped) -> None:
        # the pose and its transform travel on different topics and may arrive in either order:
        # wait (up to --tf-wait s) for the transform of the pose's own stamp, as a tf2 lookup
        # with a timeout would
        self.pending.append((msg, time.monotonic()))
        self.flush()

    def flush(self) -> None:
        """Emit the pending poses whose transform arrived (or waited long enough)."""
        child = f'{self.opts.object}_corrected'
        keep = []
        for msg, t_received in self.pending:
            stamp = stamp_to_ns(msg.header.stamp)
            tf_stamp = self.tf.stamp_of(child)
            if (tf_stamp is None or tf_stamp < stamp) \
                    and time.monotonic() - t_received < self.opts.tf_wait:
                keep.append((msg, t_received))
                continue
            self.emit_pose(msg, stamp, child)
        self.pending = keep

    def emit_pose(self, msg: PoseStamped, stamp: int, child: str) -> None:
        T = pose_to_matrix(msg.pose)
        record = {'event': 'corrected_pose', 'stamp_ns': stamp, 'frame': msg.header.frame_id,
                  'position_m': [round(float(v), 6) for v in T[:3, 3]]}
        try:
            T_target, tf_stamp = self.tf.lookup(self.opts.target_frame, child)
            record['tf_frame'] = f'{self.opts.target_frame} <- {child}'
            record['tf_stamp_ns'] = tf_stamp
            record['tf_position_m'] = [round(float(v), 6) for v in T_target[:3, 3]]
            record['tf_quaternion_xyzw'] = [round(float(v), 6)
                                            for v in quaternion_from_matrix(T_target[:3, :3])]
        except FrameLookupError as exc:
            record['tf_error'] = str(exc)
        self.emit(record)
        self.poses_seen += 1

    def on_joint(self, msg: JointEstimate) -> None:
        self.emit({'event': 'joint_estimate', 'stamp_ns': stamp_to_ns(msg.header.stamp),
                   'type': JOINT_TYPES.get(msg.joint_type, str(msg.joint_type)),
                   'frame': msg.header.frame_id,
                   'axis_in_b': [round(v, 6) for v in (msg.axis_in_b.x, msg.axis_in_b.y,
                                                       msg.axis_in_b.z)],
                   'point_in_b_m': [round(v, 6) for v in (msg.point_in_b.x, msg.point_in_b.y,
                                                          msg.point_in_b.z)],
                   'joint_position': round(msg.joint_position, 6),
                   'rotation_residual_rad': round(msg.rotation_residual, 6),
                   'position_residual_m': round(msg.position_residual, 6)})


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--object', default='peg', help='object name (default peg)')
    parser.add_argument('--target-frame', default='world',
                        help='TF frame to express the corrected pose in (default world)')
    parser.add_argument('--joint-topic', default='/joint_estimate')
    parser.add_argument('--count', type=int, default=0,
                        help='exit after this many corrected poses (0: run until Ctrl-C)')
    parser.add_argument('--timeout', type=float, default=0.0,
                        help='exit with status 1 after this many seconds (0: never)')
    parser.add_argument('--tf-wait', type=float, default=1.0,
                        help='seconds a pose waits for the transform of its stamp (default 1)')
    parser.add_argument('--json', action='store_true', help='one JSON object per line')
    opts = parser.parse_args(argv)
    rclpy.init()
    node = ControllerView(opts)
    status = 0
    try:
        deadline = node.get_clock().now().nanoseconds + int(opts.timeout * 1e9)
        while rclpy.ok() and not (opts.count and node.poses_seen >= opts.count):
            rclpy.spin_once(node, timeout_sec=0.05)
            node.flush()
            if opts.timeout and node.get_clock().now().nanoseconds > deadline:
                print(f'timed out after {opts.timeout} s with {node.poses_seen} poses',
                      file=sys.stderr)
                status = 1
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return status


if __name__ == '__main__':
    sys.exit(main())
