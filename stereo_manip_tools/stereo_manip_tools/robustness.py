"""
What every node needs to survive bad input.

counted, rate-limited rejections, a guard around callbacks, and start-up errors as one line + exit
code 1.

- :class:`InputRejections`: ``reject(reason, message)`` counts per reason and logs a warning
  at most once per second and reason (a misconfigured 30 Hz source must not flood the log);
  ``guard(callback, what)`` wraps a subscription or service callback so that a ``ValueError``
  (bad input, e.g. :class:`stereo_manip_tools.conversions.PointCloudError` with its
  ``reason``) is counted as a rejection and any other exception as ``internal_error`` with its
  type logged - the node keeps spinning instead of dying with a traceback;
- :func:`create_node_or_exit`: construct the node; a bad start-up parameter (out of range,
  wrong type, NaN, a model that does not exist) ends the process with one line on stderr and
  exit code 1 instead of an rclpy traceback;
- :func:`init_or_exit`: ``rclpy.init`` with the same treatment of unparsable ``--ros-args``.
"""

from __future__ import annotations

import functools
import sys
import time
from typing import Any, Callable, Dict, Optional, Sequence, TypeVar

import rclpy
from rclpy.exceptions import ParameterException
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor

__all__ = ['InputRejections', 'STARTUP_ERRORS', 'create_node_or_exit', 'init_or_exit',
           'spin_until_shutdown']

#: Exceptions a node constructor raises for bad start-up configuration.
STARTUP_ERRORS = (ParameterException, ValueError, TypeError, OSError, LookupError)

NodeT = TypeVar('NodeT')


class InputRejections:
    """
    Counts of rejected input per reason, with rate-limited warnings on ``logger``.

    :param period: shortest interval [s] between two warnings of the same reason.
    """

    def __init__(self, logger: Any, period: float = 1.0) -> None:
        self.logger = logger
        self.period = float(period)
        self.counts: Dict[str, int] = {}
        self._last: Dict[str, float] = {}

    @property
    def total(self) -> int:
        """Rejections of every reason."""
        return sum(self.counts.values())

    def reject(self, reason: str, message: str, *, error: bool = False) -> None:
        """Count one rejection of ``reason``; log ``message`` unless logged < period ago."""
        n = self.counts[reason] = self.counts.get(reason, 0) + 1
        now = time.monotonic()
        if now - self._last.get(reason, -1e9) < self.period:
            return
        self._last[reason] = now
        # one call site per severity: rclpy refuses a severity change at one call site
        if error:
            self.logger.error(f'{message} ({reason}: {n} so far)')
        else:
            self.logger.warning(f'{message} ({reason}: {n} so far)')

    def summary(self) -> str:
        """``'reason n, ...'`` (``'none'`` when nothing was rejected)."""
        return ', '.join(f'{k} {v}' for k, v in sorted(self.counts.items())) or 'none'

    def guard(self, callback: Callable[..., Any], what: str,
              default: Optional[Callable[..., Any]] = None) -> Callable[..., Any]:
        """
        Wrap ``callback`` so that it never raises.

        ValueError -> rejection (its ``reason`` attribute or ``'invalid'``), any other Exception ->
        ``'internal_error'``, logged with its type.

        :param default: for service callbacks, called with the callback's arguments and the
            exception to build the response returned instead.
        """
        @functools.wraps(callback)
        def guarded(*args: Any) -> Any:
            try:
                return callback(*args)
            except ValueError as exc:
                self.reject(getattr(exc, 'reason', 'invalid'), f'{what} rejected: {exc}')
                return default(*args, exc) if default is not None else None
            except Exception as exc:  # noqa: BLE001 - the node must outlive any one message
                self.reject('internal_error', f'{what}: internal error '
                            f'{type(exc).__name__}: {exc}', error=True)
                return default(*args, exc) if default is not None else None
        return guarded


def _fail(prog: str, exc: BaseException) -> None:
    text = ' '.join(str(exc).split()) or type(exc).__name__
    print(f'{prog}: {text}', file=sys.stderr, flush=True)
    rclpy.try_shutdown()
    raise SystemExit(1)


def init_or_exit(args: Optional[Sequence[str]], prog: str) -> None:
    """``rclpy.init(args=args)``; unparsable ROS arguments end the process with one line."""
    try:
        rclpy.init(args=args)
    except Exception as exc:  # noqa: BLE001 - RCLError is not importable as a stable name
        _fail(prog, exc)


def create_node_or_exit(factory: Callable[..., NodeT], prog: str, *args: Any,
                        **kwargs: Any) -> NodeT:
    """
    Return ``factory(*args, **kwargs)``, exiting cleanly on a start-up error.

    A start-up error (:data:`STARTUP_ERRORS`) prints ``<prog>: <reason>`` on stderr, shuts rclpy
    down and exits with code 1.
    """
    try:
        return factory(*args, **kwargs)
    except STARTUP_ERRORS as exc:
        _fail(prog, exc)
        raise  # unreachable: _fail exits


#: [s] longest wait of :func:`spin_until_shutdown` between checks of its context
SHUTDOWN_POLL_S = 0.5


def spin_until_shutdown(node: Any) -> None:
    """
    Spin ``node`` until Ctrl-C or an external shutdown, then destroy it and shut rclpy down.

    The end of every node's ``main()`` (the Jazzy ``demo_nodes_py`` idiom), with a bounded wait:
    the executor waits at most ``SHUTDOWN_POLL_S`` at a time and stops once the context is shut
    down. ``rclpy.spin`` waits without a timeout and relies on the signal handler waking the
    wait; measured, a peer sent SIGTERM stayed in its wait in 1 of 6 runs (faulthandler dump:
    ``wait_set.wait`` in ``_wait_for_ready_callbacks``), and ``terminate()`` then timed out.
    """
    executor = None
    try:
        executor = SingleThreadedExecutor(context=node.context)
        executor.add_node(node)
        while rclpy.ok(context=node.context):
            executor.spin_once(timeout_sec=SHUTDOWN_POLL_S)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:  # noqa: BLE001 - RCLError is not importable as a stable name
        if rclpy.ok():
            raise
        # Ctrl-C shut the context down between the executor's checks: the spin's wait set
        # fails with RCLError instead of ExternalShutdownException; a normal shutdown
    finally:
        if executor is not None:
            executor.shutdown(timeout_sec=1.0)
        node.destroy_node()
        rclpy.try_shutdown()
