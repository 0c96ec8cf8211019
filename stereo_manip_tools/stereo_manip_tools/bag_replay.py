"""
``replay``: publish a rosbag2 bag's messages onto their topics with the original timing.

Usage::

    ros2 run stereo_manip_tools replay bags/peg_in_hole --rate 0.5 --loop
    scripts/ros2run stereo_manip_tools replay BAG --topics /left/image_rect /right/image_rect

For users without a ROS install (no ``ros2 bag play``). Messages are published as the stored
CDR bytes; the spacing of the receive times is kept, divided by ``--rate``.
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Dict, Optional, Sequence

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.qos import QoSProfile, ReliabilityPolicy

from stereo_manip_tools.bag_io import bag_summary, BagError, get_message_class, read_bag

__all__ = ['main']


def parse_args(argv: Optional[Sequence[str]] = None) -> argparse.Namespace:
    """Command-line options of ``replay``."""
    p = argparse.ArgumentParser(prog='replay', description=__doc__.split('\n\n')[0])
    p.add_argument('bag', help='rosbag2 bag directory')
    p.add_argument('--rate', type=float, default=1.0, help='playback speed factor (> 0)')
    p.add_argument('--loop', action='store_true', help='start again at the end')
    p.add_argument('--topics', nargs='+', default=None, help='replay only these topics')
    p.add_argument('--delay', type=float, default=1.0,
                   help='seconds to wait after creating publishers (discovery) before playing')
    p.add_argument('--wait-subscribers', type=int, default=0, metavar='N',
                   help='before playing, wait (up to 60 s) until every replayed topic has at '
                        'least N subscribers')
    return p.parse_args(argv)


def main(args: Optional[Sequence[str]] = None) -> int:
    """Entry point; returns the exit code (0 ok, 1 user error)."""
    argv = rclpy.utilities.remove_ros_args(args if args is not None else sys.argv)[1:]
    opts = parse_args(argv)
    if not opts.rate > 0:
        print(f'replay: --rate must be > 0, got {opts.rate}', file=sys.stderr)
        return 1
    try:
        topics, start_ns, end_ns = bag_summary(opts.bag)
        wanted = {t: v for t, v in topics.items() if not opts.topics or t in opts.topics}
        missing = sorted(set(opts.topics or ()) - set(topics))
        if missing:
            raise BagError(f'topic(s) {", ".join(missing)} not in bag; it has: '
                           + ', '.join(sorted(topics)))
        classes = {t: get_message_class(mt) for t, (mt, _) in wanted.items()}
    except BagError as exc:
        print(f'replay: {exc}', file=sys.stderr)
        return 1
    rclpy.init(args=args)
    node = rclpy.create_node('bag_replayer')
    qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
    pubs = {t: node.create_publisher(cls, t, qos) for t, cls in classes.items()}
    for t, (mt, n) in wanted.items():
        print(f'[replay] {t} ({mt}): {n} messages', flush=True)
    print(f'[replay] {(end_ns - start_ns) / 1e9:.3f} s of data at rate {opts.rate:g}', flush=True)
    counts: Dict[str, int] = {t: 0 for t in pubs}
    code = 0
    try:
        time.sleep(opts.delay)
        deadline = time.monotonic() + 60.0
        while opts.wait_subscribers and any(
                p.get_subscription_count() < opts.wait_subscribers for p in pubs.values()):
            if time.monotonic() > deadline:
                print(f'replay: fewer than {opts.wait_subscribers} subscriber(s) after 60 s; '
                      'playing anyway', file=sys.stderr)
                break
            time.sleep(0.05)
        while True:
            t0_wall = time.monotonic()
            t0_bag: Optional[int] = None
            last_report = t0_wall
            for msg in read_bag(opts.bag, list(pubs)):
                if t0_bag is None:
                    t0_bag = msg.timestamp
                due = t0_wall + (msg.timestamp - t0_bag) / 1e9 / opts.rate
                delay = due - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                pubs[msg.topic].publish(msg.data)
                counts[msg.topic] += 1
                if time.monotonic() - last_report >= 1.0:
                    print(f'[replay] published {sum(counts.values())} messages', flush=True)
                    last_report = time.monotonic()
            if not opts.loop:
                break
    except BagError as exc:
        print(f'replay: {exc}', file=sys.stderr)
        code = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        print('[replay] done: ' + ', '.join(f'{t}: {n}' for t, n in counts.items()), flush=True)
        # Give late subscribers' reliable transport a moment to take the last messages.
        time.sleep(0.2)
        node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == '__main__':
    sys.exit(main())
