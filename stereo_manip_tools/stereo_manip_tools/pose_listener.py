"""
A controller-side client: subscribe to PoseStamped topics and log each pose on arrival.

Stands in for the robot controller of a multi-machine cell: it only consumes poses, and it
records, for every message, the topic, the header stamp, the wall-clock arrival time and the
pose, one JSON object per line, so the end-to-end latency (arrival - stamp, valid when the
stamp's clock and this host's clock agree) and the rate can be computed afterwards. Usage::

    python -m stereo_manip_tools.pose_listener --out poses.jsonl --duration 30 \
        /objects/peg/pose_corrected /objects/peg/pose_truth

With ``--wait-subscribed`` it first waits until the listed topics have subscribers (the rest
of the graph is up) and prints ``graph ready``. Runs until ``--duration`` seconds have passed
(or ``--count`` messages arrived on the first topic), then exits 0; ``--duration`` is required
so the process always stops by itself.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Optional, Sequence

__all__ = ['main']


def main(argv: Optional[Sequence[str]] = None) -> int:
    """Subscribe, log, stop after the duration; returns the exit code."""
    parser = argparse.ArgumentParser(prog='pose_listener', description=__doc__.split('\n\n')[0])
    parser.add_argument('topics', nargs='+', help='geometry_msgs/PoseStamped topics')
    parser.add_argument('--out', required=True, help='JSON-lines output file')
    parser.add_argument('--duration', type=float, required=True, help='seconds to listen')
    parser.add_argument('--count', type=int, default=0,
                        help='stop early after this many messages on the first topic')
    parser.add_argument('--qos', choices=('reliable', 'sensor_data'), default='reliable')
    parser.add_argument('--wait-subscribed', nargs='+', default=[], metavar='TOPIC',
                        help='first wait (within --duration) until each of these topics has a '
                             'subscriber somewhere in the graph, then print "graph ready"')
    opts = parser.parse_args(argv)
    if not opts.duration > 0:
        parser.error('--duration must be > 0')

    import rclpy
    from rclpy.executors import ExternalShutdownException
    from geometry_msgs.msg import PoseStamped

    from stereo_manip_tools.parameters import input_qos_profile

    rclpy.init()
    node = rclpy.create_node('pose_listener')
    counts = {t: 0 for t in opts.topics}
    out = open(opts.out, 'w', buffering=1)

    def on_pose(msg: PoseStamped, topic: str) -> None:
        arrival = time.time_ns()
        p, q = msg.pose.position, msg.pose.orientation
        counts[topic] += 1
        out.write(json.dumps({
            'topic': topic, 'stamp_ns': msg.header.stamp.sec * 1_000_000_000
            + msg.header.stamp.nanosec, 'arrival_ns': arrival, 'frame_id': msg.header.frame_id,
            'pose': [p.x, p.y, p.z, q.x, q.y, q.z, q.w]}) + '\n')

    qos = input_qos_profile(opts.qos, depth=10)
    for topic in opts.topics:
        node.create_subscription(PoseStamped, topic,
                                 lambda m, topic=topic: on_pose(m, topic), qos)
    node.get_logger().info(f'listening to {", ".join(opts.topics)} for {opts.duration} s')
    deadline = time.monotonic() + opts.duration
    try:
        if opts.wait_subscribed:
            while time.monotonic() < deadline and not all(
                    node.count_subscribers(t) > 0 for t in opts.wait_subscribed):
                rclpy.spin_once(node, timeout_sec=0.1)
            settle = time.monotonic() + 1.0     # let the remote ends match our writers too
            while time.monotonic() < min(settle, deadline):
                rclpy.spin_once(node, timeout_sec=0.05)
            if all(node.count_subscribers(t) > 0 for t in opts.wait_subscribed):
                print('graph ready', flush=True)
        while time.monotonic() < deadline:
            if opts.count and counts[opts.topics[0]] >= opts.count:
                break
            rclpy.spin_once(node, timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.get_logger().info(f'received {counts}')
        out.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
