"""
``record``: record chosen topics of a live graph to a rosbag2 bag (mcap or sqlite3).

Usage::

    ros2 run stereo_manip_tools record -o my_bag /left/image_rect /objects/peg/pose_truth
    scripts/ros2run stereo_manip_tools record -o my_bag --duration 5 /topic_a /topic_b

Messages are stored as received (CDR bytes) with their receive time. Ctrl-C (SIGINT), SIGTERM,
``--duration`` or ``--max-messages`` ends the recording: the recorder first drains what is
already queued for it (until ``--drain`` seconds pass without a message), then closes the bag
cleanly, so nothing that reached it is lost. Every ``--flush-period`` seconds the pending mcap
chunk is closed and flushed (sqlite3: committed), so after ``kill -9`` the bag is readable up to
that point (``read_bag``/``replay`` salvage a bag without metadata.yaml). Counts are printed
every second.
"""

from __future__ import annotations

import argparse
import signal
import sys
import time
from typing import Dict, List, Optional, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.signals import SignalHandlerOptions
from stereo_manip_tools.bag_io import BagError, BagWriter, get_message_class

__all__ = ['BagRecorder', 'main']


class BagRecorder:
    """Subscribes (raw CDR) to topics on ``node`` and writes every message to ``writer``."""

    def __init__(self, node: Node, writer: BagWriter, topics: Sequence[str]) -> None:
        self.node = node
        self.writer = writer
        self.topics = list(topics)
        self.subscriptions: Dict[str, object] = {}
        self.total = 0

    def pending_topics(self) -> List[str]:
        """Topics not yet subscribed because they have not appeared in the graph."""
        return [t for t in self.topics if t not in self.subscriptions]

    def try_subscribe(self) -> None:
        """Subscribe to every requested topic that now has a publisher with a known type."""
        known = dict(self.node.get_topic_names_and_types())
        for topic in self.pending_topics():
            if topic not in known:
                continue
            msgtype = known[topic][0]
            msg_class = get_message_class(msgtype)
            self.writer.add_topic(topic, msgtype)
            infos = self.node.get_publishers_info_by_topic(topic)
            reliable = infos and all(
                i.qos_profile.reliability == ReliabilityPolicy.RELIABLE for i in infos)
            qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE if reliable
                             else ReliabilityPolicy.BEST_EFFORT)
            self.subscriptions[topic] = self.node.create_subscription(
                msg_class, topic, lambda data, t=topic: self._on_message(t, data), qos, raw=True)
            print(f'[record] subscribed to {topic} ({msgtype}, '
                  f'{"reliable" if reliable else "best effort"})', flush=True)

    def _on_message(self, topic: str, data: bytes) -> None:
        self.writer.write(topic, self.node.get_clock().now().nanoseconds, data)
        self.total += 1


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    """Command-line options of ``record``."""
    p = argparse.ArgumentParser(prog='record', description=__doc__.split('\n\n')[0])
    p.add_argument('topics', nargs='+', help='topics to record (absolute names)')
    p.add_argument('-o', '--output', required=True, help='output bag directory (must not exist)')
    p.add_argument('--storage', choices=('mcap', 'sqlite3'), default='mcap')
    p.add_argument('--duration', type=float, default=0.0, help='stop after S seconds (0: never)')
    p.add_argument('--max-messages', type=int, default=0, help='stop after N messages in all')
    p.add_argument('--wait', type=float, default=10.0,
                   help='fail if a topic has not appeared within S seconds')
    p.add_argument('--flush-period', type=float, default=1.0,
                   help='close and flush the pending chunk every S seconds (what kill -9 can '
                        'lose at most); 0: only at the end')
    p.add_argument('--drain', type=float, default=0.5,
                   help='on stop, keep taking queued messages until none came for S seconds')
    return p.parse_args(argv)


def main(args: Optional[Sequence[str]] = None) -> int:
    """Entry point; returns the exit code (0 ok, 1 user error)."""
    argv = rclpy.utilities.remove_ros_args(args if args is not None else sys.argv)[1:]
    opts = parse_args(argv)
    try:
        writer = BagWriter(opts.output, opts.storage)
    except BagError as exc:
        print(f'record: {exc}', file=sys.stderr)
        return 1
    # Our own SIGINT/SIGTERM handlers: rclpy's would shut the context down at once, and the
    # messages already queued for the subscriptions would be lost with it.
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    stop = {'signal': None}

    def on_signal(signum: int, _frame: object) -> None:
        stop['signal'] = signal.Signals(signum).name

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    node = rclpy.create_node('bag_recorder')
    recorder = BagRecorder(node, writer, opts.topics)
    code = 0
    start = time.monotonic()
    last_report = last_flush = start
    try:
        while rclpy.ok() and stop['signal'] is None:
            recorder.try_subscribe()
            pending = recorder.pending_topics()
            now = time.monotonic()
            if pending and now - start > opts.wait:
                print(f'record: topic(s) {", ".join(pending)} did not appear within '
                      f'{opts.wait:g} s', file=sys.stderr)
                code = 1
                break
            rclpy.spin_once(node, timeout_sec=0.05)
            if now - last_report >= 1.0:
                counts = ', '.join(f'{t}: {n}' for t, n in writer.counts.items())
                print(f'[record] {recorder.total} messages ({counts})', flush=True)
                last_report = now
            if opts.flush_period > 0 and now - last_flush >= opts.flush_period:
                writer.flush()
                last_flush = now
            if opts.duration and now - start >= opts.duration:
                break
            if opts.max_messages and recorder.total >= opts.max_messages:
                break
        if stop['signal'] is not None:
            drained = _drain(node, recorder, opts.drain)
            print(f'[record] {stop["signal"]}: drained {drained} queued messages', flush=True)
    except BagError as exc:
        print(f'record: {exc}', file=sys.stderr)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        writer.close()
        counts = ', '.join(f'{t}: {n}' for t, n in writer.counts.items())
        print(f'[record] wrote {recorder.total} messages to {opts.output} ({counts})', flush=True)
        node.destroy_node()
        rclpy.try_shutdown()
        for s, handler in previous.items():
            signal.signal(s, handler)
    return code


def _drain(node: Node, recorder: BagRecorder, quiet: float, limit: float = 10.0) -> int:
    """
    Take what is queued until no message comes for ``quiet`` [s].

    Take what is queued (and still arriving) until ``quiet`` [s] pass without a message or
    ``limit`` [s] in all; returns the number of messages taken.
    """
    before = recorder.total
    t0 = last = time.monotonic()
    seen = recorder.total
    while time.monotonic() - last < quiet and time.monotonic() - t0 < limit:
        rclpy.spin_once(node, timeout_sec=0.02)
        if recorder.total != seen:
            seen = recorder.total
            last = time.monotonic()
    return recorder.total - before


if __name__ == '__main__':
    sys.exit(main())
