"""NewestOnlyWorker: a busy worker skips to the newest input; stop() ends the thread."""

import threading
import time

from stereo_manip_tools.worker import NewestOnlyWorker


def _wait(predicate, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not predicate() and time.monotonic() < deadline:
        time.sleep(0.005)
    return predicate()


def test_a_busy_worker_processes_only_the_newest_item_and_reports_the_dropped_ones():
    release = threading.Event()
    processed, replaced = [], []

    def process(item):
        processed.append(item)
        release.wait(10.0)          # busy until the test has queued more items

    worker = NewestOnlyWorker(process, 'test_worker', take=lambda item: item * 10)
    worker.start()
    try:
        with worker.lock:
            replaced.append(worker.put(1))
        assert _wait(lambda: processed == [10])          # taken (and transformed by take)
        for item in (2, 3, 4):
            with worker.lock:
                replaced.append(worker.put(item))
        release.set()
        assert _wait(lambda: len(processed) == 2)
        time.sleep(0.1)
        assert processed == [10, 40]                     # 2 and 3 were superseded
        assert replaced == [False, False, True, True]
    finally:
        release.set()
        worker.stop(timeout=5.0)
    assert not worker._thread.is_alive()


def test_take_runs_under_the_lock_and_prepare_before_the_first_item():
    events = []
    lock = threading.Lock()
    worker = NewestOnlyWorker(lambda item: events.append(('process', item)), 'test_worker',
                              lock=lock, take=lambda item: events.append(('take', lock.locked()))
                              or item, prepare=lambda: events.append(('prepare', None)))
    worker.start()
    try:
        with lock:
            assert not worker.put('a')
        assert _wait(lambda: len(events) == 3)
        assert events == [('prepare', None), ('take', True), ('process', 'a')]
    finally:
        worker.stop(timeout=5.0)
    assert not worker._thread.is_alive()


def test_stop_drops_a_pending_item_and_returns_while_idle():
    processed = []
    worker = NewestOnlyWorker(processed.append, 'test_worker')
    worker.stop(timeout=1.0)            # never started: nothing to join
    worker = NewestOnlyWorker(processed.append, 'test_worker')
    worker.start()
    t0 = time.monotonic()
    worker.stop(timeout=5.0)
    assert time.monotonic() - t0 < 2.0 and not worker._thread.is_alive() and processed == []
