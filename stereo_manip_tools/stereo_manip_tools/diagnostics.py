"""
``/diagnostics`` for stereo_manip nodes, in the manner of ``diagnostic_updater``.

``diagnostic_updater`` is not on PyPI; this module is the part of it the nodes need, publishing
``diagnostic_msgs/DiagnosticArray`` on ``/diagnostics`` (what ``diagnostic_aggregator``,
``rqt_robot_monitor`` and ``ros2 topic echo /diagnostics`` read) once per period (1 s):

- :class:`Updater`: a registry of named tasks; each fills a :class:`DiagnosticStatusWrapper`
  (level, message, key/values), published as ``"<node name>: <task name>"``;
- :class:`TopicStatus`: a frequency and latency monitor (``diagnostic_updater.FrequencyStatus``
  + ``TimeStampStatus`` in one): ``tick(stamp)`` where a message is published or received; it
  reports the rate over the last period and its mean over a window of periods, and the age of
  the stamps
  (now - header stamp: the latency from the camera exposure when stamps are the camera's)
  as median / p95 / max over the period;
- :class:`NodeDiagnostics`: the per-node hook: an Updater with a ``counters`` task that shows
  a node's counter dict and warns while a rejection counter grows, plus topic monitors.

A node's hook is one line at the end of ``__init__``:
``self.diagnostics = NodeDiagnostics(self, self.counts)``. It follows every publisher and
subscription the node has by then (rate and stamp age of each topic, without a line in the
callbacks), and turns the ``stereo_manip_msgs/TrackStatus`` messages the node publishes into the
``tracks`` task. :meth:`NodeDiagnostics.tick` and :meth:`NodeDiagnostics.set_track_state` are
there for what no topic shows.
"""

from __future__ import annotations

from collections import deque
import re
import time
from typing import Any, Callable, Deque, Dict, List, Mapping, Optional, Sequence, Tuple, \
    Union

from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
import numpy as np
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.subscription import Subscription

from stereo_manip_tools.conversions import stamp_to_ns

__all__ = [
    'OK',
    'WARN',
    'ERROR',
    'STALE',
    'LEVEL_NAMES',
    'DIAGNOSTICS_TOPIC',
    'DiagnosticStatusWrapper',
    'Updater',
    'TopicStatus',
    'NodeDiagnostics',
    'DEFAULT_WARN_PATTERN',
    'INFRASTRUCTURE_TOPICS',
]

DIAGNOSTICS_TOPIC = '/diagnostics'
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: 'OK', WARN: 'WARN', ERROR: 'ERROR', STALE: 'STALE'}

#: counter names that count lost or refused input: their growth makes the counters task WARN
#: topics :meth:`NodeDiagnostics.follow_all` leaves out
INFRASTRUCTURE_TOPICS = ('/rosout', '/parameter_events', '/diagnostics', '/tf', '/tf_static')
DEFAULT_WARN_PATTERN = r'reject|fail|drop|not_found|unpaired|invalid|error|no_fixed|timed_out|late'


class DiagnosticStatusWrapper:
    """``diagnostic_updater.DiagnosticStatusWrapper``: level, message and key/values of a task."""

    def __init__(self, name: str = '', hardware_id: str = '') -> None:
        self.name = name
        self.hardware_id = hardware_id
        self.level = OK
        self.message = ''
        self.values: List[Tuple[str, str]] = []

    def summary(self, level: int, message: str) -> None:
        """Set level and message."""
        self.level, self.message = int(level), str(message)

    def merge_summary(self, level: int, message: str) -> None:
        """Keep the worse level; join the messages of the worst level."""
        level = int(level)
        if level > self.level:
            self.level, self.message = level, str(message)
        elif level == self.level and message and level > OK:
            self.message = f'{self.message}; {message}' if self.message else str(message)

    def add(self, key: str, value: Any) -> None:
        """Add a key/value (floats with 4 significant digits)."""
        if isinstance(value, float):
            value = f'{value:.4g}'
        self.values.append((str(key), str(value)))

    def to_msg(self) -> DiagnosticStatus:
        """Return the ``diagnostic_msgs/DiagnosticStatus`` (level as the message's byte)."""
        return DiagnosticStatus(level=bytes([self.level]), name=self.name,
                                message=self.message or LEVEL_NAMES[self.level],
                                hardware_id=self.hardware_id,
                                values=[KeyValue(key=k, value=v) for k, v in self.values])


Task = Callable[[DiagnosticStatusWrapper], None]
Counters = Union[Mapping[str, int], Callable[[], Mapping[str, int]]]


class Updater:
    """
    ``diagnostic_updater.Updater``: runs the tasks every ``period`` s and publishes them.

    A task that raises is reported as ERROR with the exception text (the node keeps running).
    """

    def __init__(self, node: Node, period: float = 1.0, hardware_id: str = '') -> None:
        if not period > 0:
            raise ValueError(f'period must be > 0 s, got {period}')
        self.node = node
        self.hardware_id = hardware_id
        self.period = float(period)
        self.tasks: Dict[str, Task] = {}
        self.published = 0
        self._pub = node.create_publisher(DiagnosticArray, DIAGNOSTICS_TOPIC, 10)
        self._timer = node.create_timer(self.period, self.force_update)

    def add(self, name: str, task: Task) -> None:
        """Register (or replace) the task ``name``."""
        self.tasks[name] = task

    def remove(self, name: str) -> None:
        """Unregister a task."""
        self.tasks.pop(name, None)

    def _status_name(self, task_name: str) -> str:
        return f'{self.node.get_name()}: {task_name}'

    def run_tasks(self) -> List[DiagnosticStatusWrapper]:
        """Run every task once (what each period publishes)."""
        out = []
        for name, task in list(self.tasks.items()):
            stat = DiagnosticStatusWrapper(self._status_name(name), self.hardware_id)
            try:
                task(stat)
            except Exception as exc:  # noqa: BLE001 - a broken task must not stop the node
                stat.summary(ERROR, f'diagnostic task failed: {type(exc).__name__}: {exc}')
            out.append(stat)
        return out

    def force_update(self) -> None:
        """Run the tasks and publish one DiagnosticArray now."""
        statuses = self.run_tasks()
        if not statuses:
            return
        msg = DiagnosticArray(status=[s.to_msg() for s in statuses])
        msg.header.stamp = self.node.get_clock().now().to_msg()
        self._pub.publish(msg)
        self.published += 1


class TopicStatus:
    """
    Rate and stamp age of one topic (published or received), for a diagnostic task.

    :param min_rate: below it (Hz, over the last period) the status is WARN; 0: never.
    :param max_age: stamp age [s] whose p95 over the period above it is WARN; 0: never.
    :param window: periods in the long-run rate.
    """

    def __init__(self, name: str, min_rate: float = 0.0, max_age: float = 0.0,
                 window: int = 10, clock: Callable[[], int] = time.monotonic_ns) -> None:
        self.name = name
        self.min_rate = float(min_rate)
        self.max_age = float(max_age)
        self._clock = clock
        self.count = 0
        self._period_count = 0
        self._ages: List[float] = []
        self._history: Deque[Tuple[int, int]] = deque(maxlen=max(int(window), 1) + 1)
        self._history.append((clock(), 0))
        self.last_tick_ns: Optional[int] = None

    def tick(self, stamp: Optional[Time] = None, now_ns: Optional[int] = None) -> None:
        """
        One message.

        ``stamp``: its header stamp; ``now_ns``: the node clock's now [ns] (both needed for the
        age; without them only the rate is measured).
        """
        self.count += 1
        self._period_count += 1
        self.last_tick_ns = self._clock()
        if stamp is not None and now_ns is not None:
            stamp_ns = stamp_to_ns(stamp)
            if stamp_ns > 0:
                self._ages.append((now_ns - stamp_ns) * 1e-9)

    def run(self, stat: DiagnosticStatusWrapper) -> None:
        """Fill ``stat`` with this period's figures and start a new period."""
        now = self._clock()
        t0, c0 = self._history[-1]
        period = max((now - t0) * 1e-9, 1e-9)
        rate = self._period_count / period
        self._history.append((now, self.count))
        t_old, c_old = self._history[0]
        window_rate = (self.count - c_old) / max((now - t_old) * 1e-9, 1e-9)
        p = self.name
        stat.add(f'{p} rate [Hz]', rate)
        stat.add(f'{p} mean rate [Hz]', window_rate)      # over the last `window` periods
        stat.add(f'{p} count', self.count)
        ages = np.array(self._ages)
        if ages.size:
            stat.add(f'{p} stamp age median [s]', float(np.median(ages)))
            stat.add(f'{p} stamp age p95 [s]', float(np.percentile(ages, 95)))
            stat.add(f'{p} stamp age max [s]', float(ages.max()))
        if self.min_rate > 0 and rate < self.min_rate:
            stat.merge_summary(WARN, f'{p}: {rate:.2f} Hz < {self.min_rate:.2f} Hz')
        if self.max_age > 0 and ages.size and np.percentile(ages, 95) > self.max_age:
            stat.merge_summary(WARN, f'{p}: stamp age p95 {np.percentile(ages, 95):.3f} s > '
                                     f'{self.max_age:.3f} s')
        self._period_count = 0
        self._ages = []


class NodeDiagnostics(Updater):
    """
    The diagnostics hook of a stereo_manip node.

    Tasks: ``counters`` (every entry of ``counters``, read at each period; WARN while a counter
    whose name matches ``warn_pattern`` grew during the period), ``topics`` (one
    :class:`TopicStatus` per name passed to :meth:`tick`), and any added with :meth:`add`.

    :param counters: the node's own counter dict (kept by reference), or a callable returning one.
    :param follow: :meth:`follow_all` the node's publishers and subscriptions at construction
        (create it at the end of ``__init__``).
    """

    def __init__(self, node: Node, counters: Optional[Counters] = None,
                 period: float = 1.0, warn_pattern: str = DEFAULT_WARN_PATTERN,
                 hardware_id: str = '', follow: bool = True) -> None:
        super().__init__(node, period, hardware_id)
        self._counters = counters
        self._warn = re.compile(warn_pattern)
        self._last_counts: Dict[str, int] = {}
        self.topics: Dict[str, TopicStatus] = {}
        self._tracks: Dict[str, Tuple[str, int, Dict[str, Any], int]] = {}
        self._followed: set = set()
        if counters is not None:
            self.add('counters', self._counters_task)
        self.add('topics', self._topics_task)
        if follow:
            self.follow_all()

    def follow(self, entity: Union[Publisher, Subscription], name: str = '') -> None:
        """
        Tick ``name`` for every message ``entity`` publishes or receives.

        Tick ``name`` (default: the topic name) for every message ``entity`` -- a publisher or
        subscription of this node -- publishes or receives (by wrapping ``publish`` or the
        callback). A published ``TrackStatus`` (fields ``object_name``, ``state``, ``reason``)
        also sets that object's track state.
        """
        if not isinstance(entity, (Publisher, Subscription)):
            raise TypeError(f'cannot follow a {type(entity).__name__}')
        name = name or entity.topic_name.lstrip('/')
        self.topic(name)            # listed from now on, at 0 Hz while nothing passes
        self._followed.add(id(entity))
        if isinstance(entity, Publisher):
            publish = entity.publish

            def publish_and_tick(msg: Any) -> None:
                publish(msg)
                self._observe(name, msg)
            entity.publish = publish_and_tick
        else:
            callback = entity.callback

            def tick_and_call(msg: Any) -> Any:
                self._observe(name, msg)
                return callback(msg)
            entity.callback = tick_and_call

    def follow_all(self, exclude: Sequence[str] = INFRASTRUCTURE_TOPICS) -> None:
        """
        Follow every publisher and subscription the node has now.

        :meth:`follow` every publisher and subscription the node has now (topic names).
        """
        for entity in list(self.node.publishers) + list(self.node.subscriptions):
            if entity.topic_name not in exclude and id(entity) not in self._followed:
                self.follow(entity)

    def _observe(self, name: str, msg: Any) -> None:
        header = getattr(msg, 'header', None)
        self.tick(name, getattr(header, 'stamp', None))
        if hasattr(msg, 'object_name') and hasattr(msg, 'state'):      # TrackStatus
            state = next((k for k in dir(type(msg)) if k.isupper() and not k.startswith('_')
                          and getattr(type(msg), k) == msg.state), str(msg.state))
            values = {k: round(float(getattr(msg, k)), 4) for k in
                      ('quality', 'inlier_fraction', 'visible_residual', 'prediction_error')
                      if hasattr(msg, k)}
            reason = getattr(msg, 'reason', '')
            self.set_track_state(msg.object_name, state,
                                 WARN if state in ('LOST',) else OK,
                                 **values, **({'reason': reason} if reason else {}))

    def topic(self, name: str, min_rate: float = 0.0, max_age: float = 0.0) -> TopicStatus:
        """Return the monitor of ``name`` (created on first use)."""
        if name not in self.topics:
            self.topics[name] = TopicStatus(name, min_rate, max_age)
        return self.topics[name]

    def tick(self, name: str, stamp: Optional[Time] = None) -> None:
        """Count one message of ``name``; with its header ``stamp`` also its age."""
        now_ns = self.node.get_clock().now().nanoseconds if stamp is not None else None
        self.topic(name).tick(stamp, now_ns)

    def set_track_state(self, name: str, state: str, level: int = OK, **values: Any) -> None:
        """
        Record the track state of object ``name``.

        Record the track state of object ``name`` (shown by the ``tracks`` task, which is
        registered on first use): e.g. ``('peg', 'TRACKING', OK, quality=0.93)`` or
        ``('peg', 'LOST', WARN, reason='inlier fraction 0.2 < 0.5')``.
        """
        if 'tracks' not in self.tasks:
            self.add('tracks', self._tracks_task)
        self._tracks[name] = (state, int(level), values, self._clock_ns())

    def _clock_ns(self) -> int:
        return self.node.get_clock().now().nanoseconds

    def _tracks_task(self, stat: DiagnosticStatusWrapper) -> None:
        now = self._clock_ns()
        stat.summary(OK, ', '.join(f'{n} {s[0]}' for n, s in self._tracks.items()))
        for name, (state, level, values, t) in self._tracks.items():
            stat.add(f'{name} state', state)
            stat.add(f'{name} state age [s]', (now - t) * 1e-9)
            for key, value in values.items():
                stat.add(f'{name} {key}', value)
            if level > OK:
                stat.merge_summary(level, f'{name} {state}')

    def _counters_task(self, stat: DiagnosticStatusWrapper) -> None:
        counts = self._counters() if callable(self._counters) else self._counters
        grown = []
        for key, value in dict(counts).items():
            stat.add(key, value)
            previous = self._last_counts.get(key, 0)
            if self._warn.search(key) and isinstance(value, (int, np.integer)) \
                    and value > previous:
                grown.append(f'{key} +{value - previous}')
            self._last_counts[key] = value
        if grown:
            stat.summary(WARN, 'input lost or refused this period: ' + ', '.join(grown))
        else:
            stat.summary(OK, 'no input lost or refused this period')

    def _topics_task(self, stat: DiagnosticStatusWrapper) -> None:
        stat.summary(OK, ', '.join(f'{n} {t._period_count}' for n, t in self.topics.items())
                     + ' messages this period' if self.topics else 'no topic ticked yet')
        for t in self.topics.values():
            t.run(stat)
