"""
The recorder under signals: messages published vs recorded (tests and bench/reliability.py).

A publisher in this process sends ``std_msgs/Header`` messages (``frame_id`` = sequence number)
at a fixed rate to a ``record`` process; the recorder is signalled mid-stream while publishing
goes on, so messages are in flight when it stops. Afterwards the bag is read back (salvaged
when the recorder could not close it) and compared with what was published before the signal.
"""

from __future__ import annotations

import os
from pathlib import Path
import signal as signals
import time
from typing import Any, Dict


def recorder_trial(out_dir: Path, sig: int, *, rate_hz: float = 200.0, before_s: float = 3.0,
                   after_s: float = 0.5, flush_period: float = 0.5, storage: str = 'mcap'
                   ) -> Dict[str, Any]:
    """
    Record ``/reliability/seq`` and send ``sig`` after ``before_s`` seconds of publishing.

    :returns: counts (published before the signal, recorded, lost = published before the
        signal and missing from the bag), whether the bag was closed (metadata.yaml) and is
        readable, and whether the recorded sequence is a gap-free prefix.
    """
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Header

    from stereo_manip_tools.bag_io import BagError, get_message_class, read_bag
    from stereo_manip_tools.processes import ExecutableProcess, make_node, shutdown_node, \
        spin_until

    bag = Path(out_dir) / f'bag_{signals.Signals(sig).name}_{storage}_{time.monotonic_ns()}'
    node = make_node()
    pub = node.create_publisher(Header, '/reliability/seq',
                                QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    proc = ExecutableProcess('stereo_manip_tools', 'record',
                             ['-o', str(bag), '--storage', storage, '--flush-period',
                              str(flush_period), '/reliability/seq'])
    try:
        if not spin_until(node, lambda: pub.get_subscription_count() > 0
                          and 'subscribed to' in proc.output(), 60.0):
            raise RuntimeError('recorder did not subscribe:\n' + proc.output()[-2000:])
        spin_until(node, lambda: False, 1.0)
        period = 1.0 / rate_hz
        seq = 0
        t_start = time.monotonic()
        t_signal = None
        published_before = 0
        while True:
            now = time.monotonic()
            if t_signal is None and now - t_start >= before_s:
                published_before = seq
                os.kill(proc.process.pid, sig)
                t_signal = now
            if t_signal is not None and now - t_signal >= after_s:
                break
            pub.publish(Header(frame_id=str(seq)))
            seq += 1
            next_t = t_start + seq * period
            spin_until(node, lambda: time.monotonic() >= next_t, max(next_t - now, 0.0))
        try:
            proc.process.wait(30.0)
        except Exception:  # noqa: BLE001 - did not exit: kill it, report
            proc.process.kill()
            proc.process.wait(5.0)
        exit_code = proc.process.returncode
        output = proc.output()
    finally:
        proc.stop()
        shutdown_node(node)
    msg_class = get_message_class('std_msgs/msg/Header')
    from rclpy.serialization import deserialize_message
    try:
        recorded = [int(deserialize_message(m.data, msg_class).frame_id)
                    for m in read_bag(bag)]
        readable, error = True, ''
    except (BagError, ValueError) as exc:
        recorded, readable, error = [], False, str(exc)
    got = set(recorded)
    lost_before = [s for s in range(published_before) if s not in got]
    prefix = sorted(got) == list(range(len(got)))
    return {'signal': signals.Signals(sig).name, 'storage': storage, 'rate_hz': rate_hz,
            'flush_period_s': flush_period, 'published_total': seq,
            'published_before_signal': published_before, 'recorded': len(recorded),
            'recorded_after_signal': len([s for s in got if s >= published_before]),
            'lost_before_signal': len(lost_before), 'duplicates': len(recorded) - len(got),
            'closed_cleanly': (bag / 'metadata.yaml').exists(), 'readable': readable,
            'read_error': error, 'gap_free_prefix': prefix, 'exit_code': exit_code,
            'recorder_output_tail': output[-600:]}
