"""The stamp synchroniser pairs exactly or approximately and counts every drop; the limiter."""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from stereo_manip_tools.sync import StampRateLimiter, StampSynchronizer


def test_exact_pairs_in_any_arrival_order():
    sync = StampSynchronizer(['left', 'right', 'info'])
    assert sync.add('right', 100, 'r1') is None
    assert sync.add('info', 100, 'i1') is None
    assert sync.add('left', 100, 'l1') == {'left': 'l1', 'right': 'r1', 'info': 'i1'}
    assert sync.matched == 1


def test_exact_mode_rejects_near_stamps():
    sync = StampSynchronizer(['a', 'b'])
    sync.add('a', 100, 1)
    assert sync.add('b', 101, 2) is None


def test_approximate_mode_pairs_within_tolerance():
    sync = StampSynchronizer(['a', 'b'], tolerance_ns=5)
    sync.add('a', 100, 'a100')
    assert sync.add('b', 104, 'b104') == {'a': 'a100', 'b': 'b104'}
    sync.add('a', 200, 'a200')
    assert sync.add('b', 210, 'b210') is None


def test_unmatched_older_items_are_counted_not_silently_lost():
    sync = StampSynchronizer(['a', 'b'])
    sync.add('a', 100, 'a100')          # its partner never comes
    sync.add('a', 200, 'a200')
    assert sync.add('b', 200, 'b200') == {'a': 'a200', 'b': 'b200'}
    assert sync.dropped['superseded'] == 1
    assert sync.add('b', 150, 'late') is None
    assert sync.dropped['older_than_last_match'] == 1


def test_queue_overflow_counted():
    sync = StampSynchronizer(['a', 'b'], queue_size=2)
    for s in (1, 2, 3):
        sync.add('a', s, s)
    assert sync.dropped['queue_overflow'] == 1 and sync.pending()['a'] == [2, 3]


def test_bad_arguments():
    with pytest.raises(ValueError):
        StampSynchronizer([])
    with pytest.raises(ValueError):
        StampSynchronizer(['a'], tolerance_ns=-1)
    with pytest.raises(KeyError, match='unknown stream'):
        StampSynchronizer(['a']).add('b', 1, 1)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(0, 50), min_size=1, max_size=30, unique=True), st.randoms())
def test_every_common_stamp_matched_once_in_order(stamps, rnd):
    """
    Every common stamp is matched once, in order.

    Streams carrying the same stamps, interleaved in random order but each stream in
    increasing order, produce one set per stamp unless a partner arrives after a newer match.
    """
    sync = StampSynchronizer(['a', 'b'], queue_size=100)
    events = [('a', s) for s in sorted(stamps)] + [('b', s) for s in sorted(stamps)]
    rnd.shuffle(events)
    a = sorted([e for e in events if e[0] == 'a'], key=lambda e: e[1])
    b = sorted([e for e in events if e[0] == 'b'], key=lambda e: e[1])
    order = [a.pop(0) if (a and (not b or rnd.random() < 0.5)) else b.pop(0)
             for _ in range(len(events))]
    out = [m for k, s in order if (m := sync.add(k, s, (k, s))) is not None]
    got = [m['a'][1] for m in out]
    assert got == sorted(got) and all(m['a'][1] == m['b'][1] for m in out)
    total_dropped = sum(sync.dropped.values())
    assert len(out) * 2 + total_dropped == len(events)


def test_a_large_backward_jump_is_a_source_restart():
    sync = StampSynchronizer(('l', 'r'), restart_after_ns=10**9)
    assert sync.add('l', 5 * 10**18, 'bogus') is None
    assert sync.add('r', 5 * 10**18, 'bogus') is not None       # a set from a future stamp
    assert sync.add('l', 2 * 10**9, 'a') is None                 # far behind: restart
    assert sync.restarts == 1
    assert sync.add('r', 2 * 10**9, 'b') == {'l': 'a', 'r': 'b'}
    assert sync.add('l', 2 * 10**9 - 10, 'late') is None         # slightly older: dropped
    assert sync.dropped['older_than_last_match'] == 1 and sync.restarts == 1
    strict = StampSynchronizer(('l', 'r'), restart_after_ns=None)
    strict.add('l', 10**12, 1)
    strict.add('r', 10**12, 2)
    assert strict.add('l', 5, 3) is None and strict.dropped['older_than_last_match'] == 1


def _admitted(limiter, stamps_s):
    return [t for t in stamps_s if limiter.admit(int(round(t * 1e9)))]


def test_rate_limiter_keeps_every_third_frame_of_a_30hz_camera_at_10hz():
    lim = StampRateLimiter(10.0)
    rng = np.random.default_rng(3)
    stamps = np.arange(90) / 30.0 + rng.normal(scale=0.002, size=90)   # 2 ms jitter
    kept = _admitted(lim, stamps)
    assert len(kept) == 30 and lim.skipped == 60
    assert np.allclose(np.diff(kept), 0.1, atol=0.02)            # every third frame +- jitter
    assert abs(np.mean(np.diff(kept)) - 0.1) < 0.002


def test_rate_limiter_keeps_a_camera_at_its_own_rate_and_passes_everything_at_0():
    rng = np.random.default_rng(4)
    stamps = np.arange(50) / 10.0 + rng.normal(scale=0.005, size=50)     # 10 Hz, 5 ms jitter
    assert len(_admitted(StampRateLimiter(10.0), stamps)) == 50
    assert len(_admitted(StampRateLimiter(0.0), np.arange(50) / 30.0)) == 50
    # 12 Hz under a 10 Hz limit: 10 per second on average (a drift-free grid)
    kept = _admitted(StampRateLimiter(10.0), np.arange(120) / 12.0)
    assert 99 <= len(kept) <= 101


def test_rate_limiter_restarts_after_a_gap_or_when_stamps_go_back():
    lim = StampRateLimiter(10.0)
    assert _admitted(lim, [0.0, 0.05, 5.0, 5.02, 5.1]) == [0.0, 5.0, 5.1]
    assert lim.admit(int(1e9))          # a bag loop: stamps went back
    with pytest.raises(ValueError, match='max_rate'):
        StampRateLimiter(-1.0)
    with pytest.raises(ValueError, match='slack'):
        StampRateLimiter(10.0, slack=0.9)
