"""Process plumbing shared by every node's ``main``: init, signals, spin, clean shutdown.

rclpy's own SIGINT handler tears the context down from inside the signal, which
races with a recorder that still has to write its MCAP summary. We install our own
SIGINT/SIGTERM handlers that only set a flag; the spin loop wakes up at least every
``SPIN_TIMEOUT_S`` to look at it, then nodes are closed (``close()`` if they have
one) before the context shuts down. A configuration error is reported as one line on
stderr with exit code 2, never as a traceback.
"""
from __future__ import annotations

import signal
import sys
import threading
from typing import Callable, List, Optional, Sequence

import rclpy
from rclpy.exceptions import InvalidParameterTypeException, InvalidParameterValueException
from rclpy.executors import Executor, SingleThreadedExecutor
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

SPIN_TIMEOUT_S = 0.05
EXIT_CONFIG_ERROR = 2
ParameterException = (InvalidParameterTypeException, InvalidParameterValueException)
DRAIN_ROUNDS = 50
"""spin_once(0) calls after a stop request, so messages already delivered get handled."""


class StopFlag:
    """Set by SIGINT/SIGTERM (or by code); the spin loop polls it."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: Optional[int] = None

    def install(self) -> "StopFlag":
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                signal.signal(sig, self._handler)
        return self

    def _handler(self, signum, _frame) -> None:
        self.signal = signum
        self.event.set()

    def is_set(self) -> bool:
        return self.event.is_set()


def init(argv: Optional[Sequence[str]] = None):
    """rclpy.init without its signal handlers; returns (non-ROS args, stop flag)."""
    args = list(sys.argv if argv is None else argv)
    rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    return remove_ros_args(args)[1:], StopFlag().install()


def spin(executor: Executor, stop: StopFlag, done: Optional[Callable[[], bool]] = None,
         timeout_s: Optional[float] = None) -> bool:
    """Spin until stopped, ``done()`` or timeout (wall seconds); True if ``done()`` ended it."""
    import time

    t_end = None if timeout_s is None else time.monotonic() + timeout_s
    while rclpy.ok() and not stop.is_set():
        if done is not None and done():
            return True
        if t_end is not None and time.monotonic() > t_end:
            return False
        executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
    return bool(done and done())


def drain(executor: Executor, rounds: int = DRAIN_ROUNDS) -> None:
    for _ in range(rounds):
        if not rclpy.ok():
            return
        executor.spin_once(timeout_sec=0.0)


def close_nodes(nodes: List) -> None:
    for n in nodes:
        close = getattr(n, "close", None)
        if close is not None:
            try:
                close()
            except Exception as exc:  # keep closing the others; a recorder must still finish
                print(f"[{n.get_name()}] close failed: {exc}", file=sys.stderr)
    for n in nodes:
        try:
            n.destroy_node()
        except Exception:
            pass


def run_single(make_node: Callable[[List[str]], object], argv=None,
               done_attr: str = "done") -> int:
    """``main`` body for one node per process (what ``ros2 run`` starts)."""
    args, stop = init(argv)
    node = None
    try:
        try:
            node = make_node(args)
        except (ValueError, FileNotFoundError, LookupError, *ParameterException) as exc:
            print(f"error: {exc}", file=sys.stderr)
            return EXIT_CONFIG_ERROR
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        spin(ex, stop, done=lambda: bool(getattr(node, done_attr, False)))
        drain(ex)
        return int(getattr(node, "exit_code", 0))
    finally:
        if node is not None:
            close_nodes([node])
        rclpy.try_shutdown()
