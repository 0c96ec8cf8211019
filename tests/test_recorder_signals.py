"""
The recorder under SIGINT, SIGTERM and kill -9.

The recorder loses nothing that reached it under SIGINT/SIGTERM, and after kill -9 its bag
is readable up to the last flushed chunk (a gap-free prefix of what was published).
"""

from pathlib import Path
import signal
import sys

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from recorder_trials import recorder_trial  # noqa: E402


@pytest.mark.process
@pytest.mark.parametrize('sig', [signal.SIGINT, signal.SIGTERM])
def test_recorder_keeps_every_message_under_sigint_and_sigterm(tmp_path, sig):
    r = recorder_trial(tmp_path, sig, before_s=2.0)
    assert r['readable'] and r['closed_cleanly'], r
    assert r['exit_code'] == 0, r
    assert r['published_before_signal'] >= 300
    assert r['lost_before_signal'] == 0 and r['duplicates'] == 0, r
    assert r['gap_free_prefix'], r


@pytest.mark.process
def test_recorder_bag_after_kill_9_is_readable_up_to_the_last_flush(tmp_path):
    r = recorder_trial(tmp_path, signal.SIGKILL, before_s=2.0, flush_period=0.5)
    assert r['readable'] and not r['closed_cleanly'], r
    assert r['gap_free_prefix'] and r['duplicates'] == 0, r
    # at most one flush period (+ in flight) of the stream is lost
    assert r['recorded'] >= r['published_before_signal'] - r['rate_hz'] * 0.5 - 60, r
    assert r['recorded'] > 0
