"""
A worker thread that processes only the newest input (a one-slot mailbox).

The pattern of the nodes whose processing can be slower than their input rate
(``stereo_depth_node``, ``object_localizer_node``): the subscription callback puts each input in
the slot, replacing one not yet taken (a stale input, dropped and counted by the caller), and the
worker takes the newest whenever it is free. No rclpy here: the node owns the callbacks.
"""

from __future__ import annotations

import threading
from typing import Any, Callable, Optional

__all__ = ['NewestOnlyWorker']


class NewestOnlyWorker:
    """
    A daemon thread calling ``process(take(item))`` on the newest item put in its slot.

    :param process: called on the worker thread, without the lock, for each item taken.
    :param name: the thread's name.
    :param lock: the lock guarding the slot; the caller's own lock when its counters and the
        state read by ``take`` must change atomically with the slot (default: a new lock).
    :param take: called with the lock held when an item is taken (e.g. to snapshot parameters
        along with it); its result is what ``process`` receives (default: the item itself).
    :param prepare: called once on the worker thread before the first item (e.g. a warm-up).
    """

    def __init__(self, process: Callable[[Any], None], name: str,
                 lock: Optional[threading.Lock] = None,
                 take: Optional[Callable[[Any], Any]] = None,
                 prepare: Optional[Callable[[], None]] = None) -> None:
        self.lock = lock if lock is not None else threading.Lock()
        self._wake = threading.Condition(self.lock)
        self._process, self._take, self._prepare = process, take, prepare
        self._pending: Any = None
        self._running = True
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self) -> None:
        """Start the thread."""
        self._thread.start()

    def put(self, item: Any) -> bool:
        """
        Put ``item`` in the slot (call with :attr:`lock` held) and wake the worker.

        :returns: True when it replaced an item the worker had not taken yet (a dropped input).
        """
        replaced = self._pending is not None
        self._pending = item
        self._wake.notify()
        return replaced

    def stop(self, timeout: float) -> None:
        """Stop the thread: the item in progress finishes, a pending one is dropped."""
        with self.lock:
            self._running = False
            self._wake.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=timeout)

    def _run(self) -> None:
        if self._prepare is not None:
            self._prepare()
        while True:
            with self.lock:
                while self._running and self._pending is None:
                    self._wake.wait(0.5)
                if not self._running:
                    return
                item, self._pending = self._pending, None
                if self._take is not None:
                    item = self._take(item)
            self._process(item)
