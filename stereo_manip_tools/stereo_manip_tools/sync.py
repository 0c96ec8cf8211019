"""
Stamp synchroniser and rate limiter for message streams, by header stamp (pure Python).

Replaces ``message_filters`` (not on PyPI). With ``tolerance_ns = 0`` it matches exact stamps
(``TimeSynchronizer``); with a tolerance it matches the set whose stamps all lie within the
tolerance of each other (``ApproximateTimeSynchronizer``, simplified: the newest complete set
wins). Everything dropped is counted, by reason, in :attr:`StampSynchronizer.dropped`.
:class:`StampRateLimiter` thins a stream to a largest rate by its stamps (a throttle at the
input of a node that cannot keep up with a fast camera).
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any, Dict, Hashable, List, Optional, Sequence, Tuple

__all__ = ['StampSynchronizer', 'StampRateLimiter']


class StampSynchronizer:
    """
    Group items from the streams ``keys`` that carry the same (or nearly the same) stamp.

    :param keys: stream names, e.g. ``('left', 'right', 'left_info', 'right_info')``.
    :param tolerance_ns: largest allowed stamp spread within a set [ns]; 0 = exact.
    :param queue_size: items kept per stream while waiting for partners (older ones dropped).
    :param restart_after_ns: an item this much older than the last emitted set is a source
        restart (a camera or bag that started again, or a clock reset, or the last set came
        from a bogus future stamp): everything is forgotten and matching starts again
        (counted in ``restarts``); None: such items are dropped like any older item.
    """

    def __init__(self, keys: Sequence[Hashable], tolerance_ns: int = 0,
                 queue_size: int = 10, restart_after_ns: Optional[int] = 1_000_000_000
                 ) -> None:
        if not keys:
            raise ValueError('StampSynchronizer needs at least one stream key')
        if tolerance_ns < 0:
            raise ValueError(f'tolerance_ns must be >= 0, got {tolerance_ns}')
        if queue_size < 1:
            raise ValueError(f'queue_size must be >= 1, got {queue_size}')
        self.keys = list(keys)
        self.tolerance_ns = int(tolerance_ns)
        self.queue_size = int(queue_size)
        self._queues: Dict[Hashable, 'OrderedDict[int, Any]'] = {k: OrderedDict()
                                                                 for k in self.keys}
        self.dropped: Dict[str, int] = {'queue_overflow': 0, 'superseded': 0,
                                        'older_than_last_match': 0}
        self.matched = 0
        self.restarts = 0
        self.restart_after_ns = restart_after_ns
        self._last_match_ns: Optional[int] = None

    def add(self, key: Hashable, stamp_ns: int, item: Any) -> Optional[Dict[Hashable, Any]]:
        """
        Offer one item; returns ``{key: item}`` for every stream when a set is complete.

        Items older than the last emitted set are dropped (counted), so output stamps are
        strictly increasing - unless older by more than ``restart_after_ns``: then the source
        restarted and matching starts again from this item.

        :raises KeyError: ``key`` is not one of the streams.
        """
        if key not in self._queues:
            raise KeyError(f'unknown stream {key!r}; streams: {self.keys}')
        stamp_ns = int(stamp_ns)
        if self._last_match_ns is not None and stamp_ns <= self._last_match_ns:
            if (self.restart_after_ns is None
                    or self._last_match_ns - stamp_ns <= self.restart_after_ns):
                self.dropped['older_than_last_match'] += 1
                return None
            self.dropped['superseded'] += sum(len(q) for q in self._queues.values())
            self.reset()
            self.restarts += 1
        q = self._queues[key]
        q[stamp_ns] = item
        while len(q) > self.queue_size:
            q.popitem(last=False)
            self.dropped['queue_overflow'] += 1
        return self._try_match()

    def _try_match(self) -> Optional[Dict[Hashable, Any]]:
        if any(not q for q in self._queues.values()):
            return None
        best: Optional[Tuple[int, Dict[Hashable, int]]] = None
        # Candidate reference stamps: every stamp of the first stream, newest first.
        ref_key = self.keys[0]
        for ref in reversed(list(self._queues[ref_key])):
            chosen: Dict[Hashable, int] = {ref_key: ref}
            for k in self.keys[1:]:
                stamps = list(self._queues[k])
                nearest = min(stamps, key=lambda s: abs(s - ref))
                if abs(nearest - ref) > self.tolerance_ns:
                    break
                chosen[k] = nearest
            else:
                spread = max(chosen.values()) - min(chosen.values())
                if spread <= self.tolerance_ns:
                    best = (ref, chosen)
                    break
        if best is None:
            return None
        _, chosen = best
        newest = max(chosen.values())
        out = {k: self._queues[k].pop(s) for k, s in chosen.items()}
        for k, q in self._queues.items():
            for s in [s for s in q if s <= newest]:
                del q[s]
                self.dropped['superseded'] += 1
        self._last_match_ns = newest
        self.matched += 1
        return out

    def pending(self) -> Dict[Hashable, List[int]]:
        """Stamps waiting for partners, per stream."""
        return {k: list(q) for k, q in self._queues.items()}

    def reset(self) -> None:
        """Forget waiting items and the last match (e.g. after a bag loops back in time)."""
        for q in self._queues.values():
            q.clear()
        self._last_match_ns = None


class StampRateLimiter:
    """
    Let through at most ``max_rate`` items per second of stamps; the others are skipped.

    Items are kept on a grid of one period (1 / ``max_rate``) from the first one: an item is
    let through when its stamp has reached the next grid point, less ``slack`` of a period
    (camera stamps jitter), and the grid then moves on by a period (no drift: a 10 Hz camera
    under a 10 Hz limit keeps every frame, a 30 Hz one every third). After a gap of more than
    a period the grid restarts at the item; a stamp that goes back (a bag loop, a restarted
    camera) restarts it too. ``max_rate`` 0: everything passes.

    :param max_rate: largest rate [Hz of stamps]; 0 = no limit.
    :param slack: share of a period by which an item may be early, in [0, 0.5].
    """

    def __init__(self, max_rate: float = 0.0, slack: float = 0.25) -> None:
        if not max_rate >= 0.0:
            raise ValueError(f'max_rate must be >= 0 Hz, got {max_rate}')
        if not 0.0 <= slack <= 0.5:
            raise ValueError(f'slack must be in [0, 0.5], got {slack}')
        self.max_rate = float(max_rate)
        self.slack = float(slack)
        self.skipped = 0
        self._due_ns: Optional[int] = None
        self._last_ns: Optional[int] = None

    def admit(self, stamp_ns: int) -> bool:
        """Return whether the item stamped ``stamp_ns`` passes (else it is counted skipped)."""
        if self.max_rate <= 0.0:
            return True
        period = int(round(1e9 / self.max_rate))
        if (self._due_ns is None or self._last_ns is None or stamp_ns < self._last_ns
                or stamp_ns > self._due_ns + period):
            self._due_ns, self._last_ns = stamp_ns + period, stamp_ns
            return True
        if stamp_ns < self._due_ns - self.slack * period:
            self.skipped += 1
            return False
        self._due_ns += period
        self._last_ns = stamp_ns
        return True
