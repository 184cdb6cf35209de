"""Process plumbing shared by every node's ``main``: init, signals, spin, clean shutdown.

rclpy's own SIGINT handler tears the context down from inside the signal, which
races with a recorder that still has to write its MCAP summary. We install our own
SIGINT/SIGTERM handlers that only set a flag; the spin loop wakes up at least every
``SPIN_TIMEOUT_S`` to look at it, then nodes are closed (``close()`` if they have
one) before the context shuts down. A configuration error is reported as one line on
stderr with exit code 2, never as a traceback.
"""
from __future__ import annotations

import gc
import os
import signal
import sys
import threading
import time
from typing import Callable, List, Optional, Sequence

import rclpy
from rclpy.exceptions import (InvalidParameterTypeException, InvalidParameterValueException,
                              NameValidationException)
from rclpy.executors import (Executor, ExternalShutdownException, ShutdownException, SingleThreadedExecutor,
                              TimeoutException)
from rclpy.signals import SignalHandlerOptions
from rclpy.utilities import remove_ros_args

from .params import ConfigError, warn_undeclared_file_parameters

SPIN_TIMEOUT_S = 0.05
EXIT_CONFIG_ERROR = 2
ParameterException = (InvalidParameterTypeException, InvalidParameterValueException)
# what building a node from bad parameters raises besides ValueError: an invalid topic, service or
# node name (a name parameter), and rcl's own refusal of a value it checks (e.g. a timer period)
try:
    from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy_impl
    SetupException = (*ParameterException, NameValidationException, _rclpy_impl.RCLError)
except (ImportError, AttributeError):  # pragma: no cover - other rclpy layouts
    SetupException = (*ParameterException, NameValidationException)
DRAIN_TIMEOUT_S = 10.0
"""After a stop request a node handles every callback already ready (messages delivered before
the stop, a recorder's backlog on a loaded machine) until none is, for at most this long: a
source that keeps publishing faster than the node handles it cannot hold the stop up for ever."""
DRAIN_CUT_WARNING = (f"stopping with callbacks still ready after {DRAIN_TIMEOUT_S:g} s of handling them: "
                     "a source publishes faster than this node handles it")


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


DEFAULT_DISCOVERY_RANGE = "LOCALHOST"


WARN_THROTTLE_S = 1.0
"""Per call site: a flood of bad messages gives one warning a second, not one per message."""
ERROR_LINE_MAX = 400
"""Characters of an error line: some library messages (torch) run to paragraphs."""


def one_line(exc) -> str:
    """The first line of an exception's text, capped: exit-code-2 errors are one line."""
    text = str(exc).strip().splitlines()
    line = text[0] if text else type(exc).__name__
    return line if len(line) <= ERROR_LINE_MAX else line[:ERROR_LINE_MAX] + " ..."


def init(argv: Optional[Sequence[str]] = None):
    """rclpy.init without its signal handlers; returns (non-ROS args, stop flag).

    A broken ``--params-file`` (YAML rcl cannot parse) surfaces here as an RCLError;
    it becomes a :class:`ConfigError` naming the problem.
    """
    from rclpy._rclpy_pybind11 import RCLError
    # discovery stays on this machine unless the user asks for more (SUBNET for a
    # multi-machine deployment): a default must not expose the graph to the network
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", DEFAULT_DISCOVERY_RANGE)
    args = list(sys.argv if argv is None else argv)
    try:
        rclpy.init(args=args, signal_handler_options=SignalHandlerOptions.NO)
    except RCLError as exc:
        raise ConfigError(f"bad ROS arguments or parameter file: {one_line(exc)}") from None
    return remove_ros_args(args)[1:], StopFlag().install()


def guarded(node, what: str, fn: Callable, errors: Optional[dict] = None) -> Callable:
    """Wrap a subscription callback so that no message can take the node down.

    A message the converters reject (``MessageError``, incl. stale/out-of-order stamps)
    is dropped with a throttled warning; any other exception raised while handling one
    message (a core function refusing an input it cannot use) is dropped with a
    throttled error naming the exception. ``errors`` (topic -> count) is incremented per
    dropped message, for tests and diagnostics.
    """
    from bimacppo_interfaces.contract import MessageError
    log = node.get_logger()

    def cb(msg):
        try:
            fn(msg)
        except MessageError as exc:
            if errors is not None:
                errors[what] = errors.get(what, 0) + 1
            log.warning(f"ignored {what}: {exc}", throttle_duration_sec=WARN_THROTTLE_S)
        except Exception as exc:  # noqa: BLE001 - one bad message must not kill the node
            if errors is not None:
                errors[what] = errors.get(what, 0) + 1
            log.error(f"dropped {what}: {type(exc).__name__}: {one_line(exc)}",
                      throttle_duration_sec=WARN_THROTTLE_S)
    return cb


def spin(executor: Executor, stop: StopFlag, done: Optional[Callable[[], bool]] = None,
         timeout_s: Optional[float] = None) -> bool:
    """Spin until stopped, ``done()`` or timeout (wall seconds); True if ``done()`` ended it."""
    t_end = None if timeout_s is None else time.monotonic() + timeout_s
    while rclpy.ok() and not stop.is_set():
        if done is not None and done():
            return True
        if t_end is not None and time.monotonic() > t_end:
            return False
        executor.spin_once(timeout_sec=SPIN_TIMEOUT_S)
    return bool(done and done())


def _never() -> bool:
    return False


def drain(executor: Executor, timeout_s: float = DRAIN_TIMEOUT_S) -> bool:
    """Handle the callbacks that are ready until none is; False if ``timeout_s`` (wall seconds)
    ran out first, with callbacks still ready (the caller warns), True otherwise, also when the
    context shut down: then nothing more can be handled.

    A fixed number of ``spin_once`` calls is not enough: each handles one callback, and a
    recorder that lags its graph by a few hundred messages when it is stopped would lose the
    rest, although DDS had delivered them."""
    t_end = time.monotonic() + timeout_s
    handled = False     # a callback since the last zero-timeout wait ended
    while rclpy.ok():
        if time.monotonic() > t_end:
            return False
        try:
            # the arguments spin_once passes, so both use the executor's one ready-callback iterator
            handler, _, _ = executor.wait_for_ready_callbacks(0.0, None, _never)
        except TimeoutException:
            # a zero-timeout wait ends after handing out what one wait found: idle only if a
            # whole wait found nothing
            if not handled:
                return True
            handled = False
            continue
        except (ShutdownException, ExternalShutdownException):
            return True
        handled = True
        handler()
        if handler.exception() is not None:
            raise handler.exception()
    return True


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


def optional_path_arg(args: List[str], usage: str) -> Optional[str]:
    """The one optional positional path of a bag tool (``mcap_recorder [OUTPUT.mcap]``): None
    without one; a second one, or an option before ``--ros-args`` (``--verbose``), is no path:
    ``ValueError`` with the usage line (run_single turns it into one ``error:`` line, exit 2)."""
    if len(args) > 1 or any(a.startswith("-") for a in args):
        raise ValueError(f"usage: {usage} (got {args})")
    return args[0] if args else None


def close_executor(ex) -> None:
    """Shut an executor down while its context is still alive. Left to the garbage collector
    after ``rclpy.shutdown``, its destructor touches the context's SIGINT guard condition, which
    is already destroyed, and prints an ignored-exception traceback at exit."""
    if ex is not None:
        try:
            ex.shutdown(timeout_sec=1.0)
        except Exception:
            pass


def node_usage(make_node: Callable) -> str:
    """``--help`` of a node executable: how ROS arguments are passed, then the docstring of the
    module that defines the node (what it does, its topics and parameters)."""
    import inspect
    prog = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else "node"
    module = inspect.getmodule(make_node)
    doc = inspect.cleandoc(module.__doc__) if module is not None and module.__doc__ else ""
    head = (f"usage: {prog} [--ros-args [-p NAME:=VALUE ...] [--params-file FILE] [-r FROM:=TO ...]]\n"
            "Parameters are ROS parameters (declared with ranges and descriptions; `ros2 param describe`\n"
            "shows them); docs/parameters.md lists every node's parameters.")
    return head + ("\n\n" + doc if doc else "")


def run_single(make_node: Callable[[List[str]], object], argv=None,
               done_attr: str = "done") -> int:
    """``main`` body for one node per process (what ``ros2 run`` starts)."""
    try:
        args, stop = init(argv)
    except ConfigError as exc:
        print(f"error: {one_line(exc)}", file=sys.stderr)
        return EXIT_CONFIG_ERROR
    node = None
    ex = None
    try:
        if "-h" in args or "--help" in args:
            print(node_usage(make_node))
            return 0
        try:
            node = make_node(args)
        except (ValueError, FileNotFoundError, LookupError, *SetupException) as exc:
            print(f"error: {one_line(exc)}", file=sys.stderr)
            return EXIT_CONFIG_ERROR
        warn_undeclared_file_parameters(node, sys.argv if argv is None else argv)
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        spin(ex, stop, done=lambda: bool(getattr(node, done_attr, False)))
        if not drain(ex):
            node.get_logger().warning(DRAIN_CUT_WARNING)
        return int(getattr(node, "exit_code", 0))
    finally:
        if node is not None:
            close_nodes([node])
        else:
            # a node whose constructor raised is unreachable, but its rcl handles may sit in a
            # reference cycle; collect it now, while its context is alive, not at interpreter exit
            gc.collect()
        close_executor(ex)
        rclpy.try_shutdown()
