"""
Malformed-message fuzzing of nodes running as their own processes (tests and benchmarks).

- hypothesis strategies for malformed ``PointCloud2``, ``PoseStamped``, ``Image`` and
  ``CameraInfo`` messages: broken layouts (point_step 0, offsets beyond point_step, datatypes 0
  or 99, truncated data, huge declared sizes), NaN/inf/1e30 values, zero and non-unit
  quaternions, degenerate geometry (collinear, identical points), stamps anywhere in range;
- :class:`FuzzTarget` describes a node: how to start it, its inputs (topic -> type and the
  strategy of malformed messages), the good messages of cycle ``k`` and the check of its output
  for them;
- :class:`FuzzSession` runs the node, publishes a malformed burst then the good messages of a
  cycle, and reports whether the node survived and produced the correct output for the good
  input (restarting it after a crash, so a campaign counts every crash).
"""

from __future__ import annotations

from dataclasses import dataclass, field
import math
import time
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

import numpy as np

__all__ = ['SPECIAL_FLOATS', 'stamps', 'malformed_pointcloud2', 'malformed_pose_stamped',
           'malformed_image', 'malformed_camera_info', 'FuzzTarget', 'CycleResult',
           'FuzzSession']

#: Values that break arithmetic: NaN, infinities, overflow to inf in float32, denormals.
SPECIAL_FLOATS = (math.nan, math.inf, -math.inf, 1e30, -1e30, 3.5e38, 1e-40, 0.0, -0.0)


def _st():
    from hypothesis import strategies as st
    return st


def stamps():
    """``builtin_interfaces/Time`` anywhere in its range (0, far future, ...)."""
    st = _st()
    from builtin_interfaces.msg import Time
    return st.builds(lambda s, ns: Time(sec=s, nanosec=ns),
                     st.one_of(st.just(0), st.integers(0, 2**31 - 1)),
                     st.integers(0, 999_999_999))


def _header():
    st = _st()
    from std_msgs.msg import Header
    return st.builds(lambda stamp, frame: Header(stamp=stamp, frame_id=frame), stamps(),
                     st.one_of(st.just(''), st.just('stereo_left_optical'),
                               st.text(max_size=40)))


def _floats():
    st = _st()
    return st.one_of(st.sampled_from(SPECIAL_FLOATS),
                     st.floats(-10.0, 10.0, allow_nan=False, width=32))


def malformed_pointcloud2(max_points: int = 3000):
    """
    PointCloud2 messages that are wrong in layout or content (never a clean object cloud).

    :param max_points: largest cloud of the content variants (bounds the campaign's time).
    """
    st = _st()
    from sensor_msgs.msg import PointCloud2, PointField

    xyz_fields = [PointField(name=n, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, n in enumerate('xyz')]

    def cloud(points: np.ndarray, header: Any, **change: Any) -> PointCloud2:
        with np.errstate(over='ignore'):          # 1e30 stays, 3.5e38 becomes inf: wanted
            P = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        msg = PointCloud2(header=header, height=1, width=len(P), fields=list(xyz_fields),
                          point_step=12, row_step=12 * len(P), is_dense=False,
                          data=P.tobytes())
        for k, v in change.items():
            setattr(msg, k, v)
        return msg

    field_st = st.builds(lambda name, offset, datatype, count: PointField(
        name=name, offset=offset, datatype=datatype, count=count),
        st.sampled_from(['x', 'y', 'z', 'rgb', 'normal_x', 'intensity']),
        st.integers(0, 64), st.one_of(st.sampled_from([0, 7, 8, 99]), st.integers(0, 255)),
        st.integers(0, 4))
    random_layout = st.builds(
        lambda header, w, h, ps, rs, fields, big, data: PointCloud2(
            header=header, width=w, height=h, point_step=ps, row_step=rs, fields=fields,
            is_bigendian=big, data=data),
        _header(), st.integers(0, 200), st.integers(0, 4), st.integers(0, 64),
        st.integers(0, 2000), st.lists(field_st, max_size=7), st.booleans(),
        st.binary(max_size=4000))
    special_values = st.builds(
        lambda header, vals: cloud(np.array(vals, dtype=np.float64).reshape(-1, 3), header),
        _header(), st.lists(_floats(), min_size=0, max_size=300).map(
            lambda v: v[:len(v) - len(v) % 3]))

    def degenerate(header: Any, kind: str, n: int, seed: int) -> PointCloud2:
        rng = np.random.default_rng(seed)
        t = rng.random(n)
        if kind == 'collinear':
            P = np.c_[t * 0.2, t * 0.1, 0.5 + t * 0.05]
        elif kind == 'identical':
            P = np.tile([0.01, -0.02, 0.6], (n, 1))
        elif kind == 'planar':
            P = np.c_[rng.random(n) * 0.2, rng.random(n) * 0.2, np.full(n, 0.5)]
        elif kind == 'noise':
            P = (rng.random((n, 3)) - 0.5) * 4.0 + [0, 0, 2.0]
        else:                       # far away: a valid cloud 1 km off
            P = rng.random((n, 3)) + [0, 0, 1000.0]
        return cloud(P, header)
    degenerate_st = st.builds(degenerate, _header(),
                              st.sampled_from(['collinear', 'identical', 'planar', 'noise',
                                               'far']),
                              st.integers(1, max_points), st.integers(0, 2**16))

    def broken(header: Any, how: str, seed: int) -> PointCloud2:
        rng = np.random.default_rng(seed)
        P = rng.random((50, 3)) * 0.1 + [0, 0, 0.5]
        changes = {
            'point_step_0': {'point_step': 0},
            'point_step_1': {'point_step': 1},
            'offset_beyond': {'fields': xyz_fields[:2] + [PointField(
                name='z', offset=200, datatype=7, count=1)]},
            'datatype_0': {'fields': [PointField(name='x', offset=0, datatype=0, count=1)]
                           + xyz_fields[1:]},
            'datatype_99': {'fields': [PointField(name='x', offset=0, datatype=99, count=1)]
                            + xyz_fields[1:]},
            'big_endian': {'is_bigendian': True},
            'declared_larger': {'width': 10**6},
            'declared_huge': {'width': 2**31, 'height': 2**31 - 1},
            'row_step_small': {'height': 5, 'width': 10, 'row_step': 3},
            'no_fields': {'fields': []},
            'duplicate_field': {'fields': xyz_fields + [xyz_fields[0]]},
            'float64_declared': {'fields': [PointField(name=n, offset=8 * i, datatype=8,
                                                       count=1) for i, n in enumerate('xyz')]},
            'empty': {'width': 0, 'data': b''},
            'height_0': {'height': 0},
        }[how]
        return cloud(P, header, **changes)
    broken_st = st.builds(broken, _header(), st.sampled_from(
        ['point_step_0', 'point_step_1', 'offset_beyond', 'datatype_0', 'datatype_99',
         'big_endian', 'declared_larger', 'declared_huge', 'row_step_small', 'no_fields',
         'duplicate_field', 'float64_declared', 'empty', 'height_0']), st.integers(0, 2**16))
    return st.one_of(broken_st, random_layout, special_values, degenerate_st)


def malformed_pose_stamped():
    """Draw PoseStamped with NaN/inf/huge positions, zero/NaN/non-unit quaternions, odd stamps."""
    st = _st()
    from geometry_msgs.msg import Point, Pose, PoseStamped, Quaternion

    quat = st.one_of(
        st.just((0.0, 0.0, 0.0, 0.0)),
        st.tuples(_floats(), _floats(), _floats(), _floats()),
        st.sampled_from([1e-12, 1e12, 2.0]).map(lambda s: (0.0, 0.0, 0.0, s)))
    position = st.tuples(_floats(), _floats(), _floats())
    return st.builds(
        lambda header, p, q: PoseStamped(header=header, pose=Pose(
            position=Point(x=p[0], y=p[1], z=p[2]),
            orientation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3]))),
        _header(), position, quat)


def malformed_image(encodings: Sequence[str] = ('mono8', 'mono16', 'rgb8', 'bgra8', '32FC1')):
    """Images with wrong or unknown encodings, steps, sizes, byte order and data lengths."""
    st = _st()
    from sensor_msgs.msg import Image

    def image(header: Any, enc: str, w: int, h: int, step_delta: int, data_delta: int,
              big: bool, huge: bool) -> Image:
        bpp = {'mono8': 1, 'mono16': 2, 'rgb8': 3, 'bgra8': 4, '32FC1': 4}.get(enc, 1)
        step = max(w * bpp + step_delta, 0)
        n = max(h * step + data_delta, 0)
        if huge:
            w, h, step = 100_000, 100_000, 100_000 * bpp
        return Image(header=header, height=h, width=w, encoding=enc, is_bigendian=big,
                     step=step, data=bytes(np.random.default_rng(n).integers(
                         0, 256, size=min(n, 200_000), dtype=np.uint8)))
    return st.builds(image, _header(),
                     st.one_of(st.sampled_from(list(encodings)),
                               st.sampled_from(['yuv422', 'bayer_rggb8', '', '16UC3', '8SC1']),
                               st.text(max_size=12)),
                     st.integers(0, 160), st.integers(0, 120), st.integers(-8, 8),
                     st.integers(-64, 64), st.booleans(),
                     st.sampled_from([False] * 9 + [True]))


def malformed_camera_info():
    """Draw CameraInfo with zero/NaN/negative projections, odd sizes and distortion lengths."""
    st = _st()
    from sensor_msgs.msg import CameraInfo

    nine = st.lists(_floats(), min_size=9, max_size=9)
    twelve = st.one_of(
        st.lists(_floats(), min_size=12, max_size=12),
        st.sampled_from([[0.0] * 12, [100.0, 0, 48, 10.0, 0, 100, 32, 0, 0, 0, 1, 0],
                         [100.0, 0, 48, -1e30, 0, 100, 32, 0, 0, 0, 1, 0]]))
    return st.builds(
        lambda header, w, h, d, k, r, p, model: CameraInfo(
            header=header, width=w, height=h, d=d, k=k, r=r, p=p, distortion_model=model),
        _header(), st.integers(0, 2**32 - 1), st.integers(0, 2**32 - 1),
        st.lists(_floats(), max_size=20), nine, nine, twelve,
        st.sampled_from(['plumb_bob', 'rational_polynomial', '', 'garbage']))


@dataclass
class FuzzTarget:
    """
    A node under fuzzing.

    :ivar inputs: topic -> (message class, strategy of malformed messages; a strategy may
        also give ``(topic, msg)`` lists, e.g. a stereo pair with one stamp).
    :ivar good: cycle ``k`` -> the good messages [(topic, msg), ...] (published in order;
        their stamps increase with ``k``).
    :ivar outputs: topic -> message class the node publishes.
    :ivar check: ``(received {topic: [msg]}, k)`` -> None when cycle k's output is present
        and correct, else the reason (None also means "done waiting").
    :ivar good_gap: seconds between two good messages (order across topics is not kept by
        DDS: e.g. the fixed pose must have arrived before the moving one).
    :ivar pacing: seconds between two malformed messages (the nodes keep a short input
        queue: without pacing most of a burst would be replaced before being read).
    """

    name: str
    package: str
    executable: str
    node_name: str
    ros_args: List[str]
    inputs: Dict[str, Tuple[Any, Any]]
    good: Callable[[int], List[Tuple[str, Any]]]
    outputs: Dict[str, Any]
    check: Callable[[Dict[str, List[Any]], int], Optional[str]]
    timeout: float = 20.0
    pacing: float = 0.02
    qos_depth: int = 50
    burst_strategy: Any = None
    settle: float = 1.0
    good_gap: float = 0.005
    extra: Dict[str, Any] = field(default_factory=dict)


@dataclass
class CycleResult:
    """One burst + good input: did the node survive, was the good input processed right."""

    cases: int
    crashed: bool
    good_ok: bool
    reason: str
    seconds_to_good_output: float


class FuzzSession:
    """The target node as a process, plus an in-process observer publishing and listening."""

    def __init__(self, target: FuzzTarget, observer: Any = None) -> None:
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        from stereo_manip_tools.processes import make_node

        self.target = target
        self.own_observer = observer is None
        self.observer = observer if observer is not None else make_node()
        qos = QoSProfile(depth=target.qos_depth, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs = {t: self.observer.create_publisher(cls, t, qos)
                     for t, (cls, _) in target.inputs.items()}
        self.received: Dict[str, List[Any]] = {t: [] for t in target.outputs}
        self.subs = [self.observer.create_subscription(
            cls, t, lambda m, t=t: self.received[t].append(m), qos)
            for t, cls in target.outputs.items()]
        self.proc: Any = None
        self.crashes = 0
        self.crash_logs: List[str] = []
        self.cycle = 0
        self.start()

    def start(self) -> None:
        """Start (or restart) the node and wait until it is matched to every input."""
        from stereo_manip_tools.testing import start_executable, wait_for_subscribers

        t = self.target
        self.proc = start_executable(t.package, t.executable, ros_args=t.ros_args,
                                     observer=self.observer, wait_for_node=t.node_name,
                                     timeout=60.0)
        if not wait_for_subscribers(self.observer, list(self.pubs.values()), 30.0, t.settle):
            raise RuntimeError(f'{t.name}: inputs not matched; output:\n'
                               + self.proc.output()[-3000:])

    def spin(self, seconds: float) -> None:
        from stereo_manip_tools.processes import spin_until
        spin_until(self.observer, lambda: False, seconds)

    def publish(self, topic: str, msg: Any) -> None:
        self.pubs[topic].publish(msg)

    def run_cycle(self, burst: Sequence[Tuple[str, Any]],
                  timeout: Optional[float] = None) -> CycleResult:
        """
        Publish ``burst`` (paced), then cycle ``k``'s good messages.

        Wait (``timeout`` [s], default the target's) for the checked output. A node that died is
        restarted (and counted).
        """
        from stereo_manip_tools.processes import spin_until

        k = self.cycle
        self.cycle += 1
        for topic, msg in burst:
            self.publish(topic, msg)
            self.spin(self.target.pacing)
        crashed = not self.proc.running()
        t0 = time.monotonic()
        reason: Optional[str] = 'not checked'
        if not crashed:
            for topic, msg in self.target.good(k):
                self.publish(topic, msg)
                self.spin(self.target.good_gap)

            def done() -> bool:
                nonlocal reason
                reason = self.target.check(self.received, k)
                return reason is None or not self.proc.running()
            spin_until(self.observer, done, timeout or self.target.timeout)
            crashed = not self.proc.running()
        elapsed = time.monotonic() - t0
        if crashed:
            self.crashes += 1
            self.crash_logs.append(self.proc.output()[-4000:])
            self.proc.stop()
            self.start()
            return CycleResult(len(burst), True, False, 'node exited', elapsed)
        return CycleResult(len(burst), False, reason is None, reason or '', elapsed)

    def close(self) -> str:
        """Stop the node; returns its output."""
        out = ''
        if self.proc is not None:
            self.proc.stop()
            out = self.proc.output()
            self.proc.__exit__(None, None, None)
        for sub in self.subs:
            self.observer.destroy_subscription(sub)
        for pub in self.pubs.values():
            self.observer.destroy_publisher(pub)
        if self.own_observer:
            from stereo_manip_tools.processes import shutdown_node
            shutdown_node(self.observer)
        return out


def burst_strategy(target: FuzzTarget, min_size: int = 1, max_size: int = 10):
    """Draw lists of ``(topic, msg)`` from the target's malformed-message strategies."""
    st = _st()
    if target.burst_strategy is not None:
        return target.burst_strategy
    per_topic = [st.tuples(st.just(topic), strategy)
                 for topic, (_, strategy) in target.inputs.items()]
    return st.lists(st.one_of(per_topic), min_size=min_size, max_size=max_size)
