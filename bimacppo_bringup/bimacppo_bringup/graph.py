"""The demo: every node of the composition in one process.

    bimacppo-graph --episodes 5 --output run.mcap [--policy PATH] [--mode lockstep|realtime]

The nodes, their params files, shared parameters and arguments are those of
``bimacppo_bringup.composition``, the table the launch file reads too; a flag is an argument of
that table (``--seed-base`` is ``seed_base``) and its default is the params file's value.
Two flags spell the switches the way a command line reads: ``--no-record`` (``record:=false``)
and ``--live-view [PORT]`` (``live_view:=true``, and ``port`` when given); ``--timeout`` is the
only flag of this process alone.

Executor: ``SingleThreadedExecutor``. The nodes are Python and CPU-bound, so threads
would only contend for the GIL; the lockstep loop is sequential by construction
(state -> reference -> command -> step); and one thread makes callback order, hence
a run, reproducible. Everything still goes through DDS exactly as across processes,
so this is the same graph as ``ros2 launch`` of the composition (docs/ros.md).
Prints success / collision / timeout counts and the MCAP path at the end.
"""
from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys
import time
from collections import Counter

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from bimacppo_common.conventions import OUTCOMES
from bimacppo_interfaces import contract as I
from bimacppo_ros_common import runtime
from bimacppo_ros_common.params import ConfigError

from . import composition as C

PROG = "bimacppo-graph"


def share_of(package: str) -> str:
    """Where a package's config/ lies: its installed share directory (colcon), else its source
    folder (an editable install into a virtual environment installs no share/)."""
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
        try:
            share = get_package_share_directory(package)
            if os.path.isdir(os.path.join(share, "config")):
                return share
        except PackageNotFoundError:
            pass
    except ImportError:
        pass
    spec = importlib.util.find_spec(package)
    origin = getattr(spec, "origin", None) if spec is not None else None
    if origin:
        root = os.path.dirname(os.path.dirname(origin))
        if os.path.isfile(os.path.join(root, "package.xml")):
            return root
    raise ConfigError(f"package {package} has no share/{package}/config (install it with colcon, "
                      "or editable with scripts/install.sh)")


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def build_parser(defaults) -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    for a in C.ARGUMENTS:
        if not a.targets:
            continue
        d = defaults[a.name]
        kind = type(d) if isinstance(d, (int, float, str)) and not isinstance(d, bool) else str
        ap.add_argument(_flag(a.name), dest=a.name, type=kind, default=d, help=f"{a.help} (default: {d!r})")
    ap.add_argument("--no-record", dest="record", action="store_false", default=defaults["record"],
                    help="do not run the MCAP recorder")
    ap.add_argument("--live-view", nargs="?", type=int, const=None, default=False, metavar="PORT",
                    help="serve the graph to Foxglove on ws://127.0.0.1:PORT (default port: the "
                         "live view's params file; bimacppo_viz, docs/live-view.md)")
    ap.add_argument("--timeout", type=float, default=0.0, help="wall-clock limit in s (0 = none)")
    return ap


def argument_values(args) -> dict:
    """The composition's argument values from parsed flags (switches included)."""
    values = {a.name: getattr(args, a.name) for a in C.ARGUMENTS if a.targets}
    values["record"] = bool(args.record)
    values["live_view"] = args.live_view is not False
    if args.live_view not in (False, None):
        values["port"] = args.live_view
    if set(values) != {a.name for a in C.ARGUMENTS}:
        raise ValueError(f"flags and the composition's arguments differ: {sorted(values)}")
    return values


def node_class(e: C.NodeEntry):
    mod, _, name = e.node_class.partition(":")
    try:
        return getattr(importlib.import_module(mod), name)
    except ImportError as exc:
        raise LookupError(f"{e.name}: {e.node_class} is not importable (is {e.package} installed? "
                          f"scripts/install.sh installs every package): {exc}") from None


def build_nodes(values) -> list:
    """Every running node of the composition, with the parameters the launch file gives it."""
    nodes = []
    try:
        for e, params in C.compose(values, share_of):
            cls = node_class(e)
            nodes.append(cls(parameter_overrides=[Parameter(k, value=v) for k, v in params.items()]))
    except BaseException:
        runtime.close_nodes(nodes)
        raise
    return nodes


def run(args, values) -> int:
    nodes = []
    ex = SingleThreadedExecutor()
    stop = runtime.StopFlag().install()
    try:
        nodes = build_nodes(values)
        by_name = {n.get_name(): n for n in nodes}
        cur = by_name[I.CURRICULUM_NODE]
        for n in nodes:
            ex.add_node(n)
        rec = by_name.get(I.RECORDER_NODE)
        if rec is not None:
            rec.discover()  # subscribe before the first episode starts
        t0 = time.monotonic()
        finished = runtime.spin(ex, stop, done=lambda: cur.done,
                                timeout_s=args.timeout if args.timeout > 0 else None)
        if not runtime.drain(ex):
            print(runtime.DRAIN_CUT_WARNING, file=sys.stderr)
        wall = time.monotonic() - t0
        counts = Counter(r[3] for r in cur.results)
        n = max(len(cur.results), 1)
        print(f"episodes: {len(cur.results)}  " + "  ".join(
            f"{k}: {counts.get(k, 0)} ({100.0 * counts.get(k, 0) / n:.0f}%)"
            for k in OUTCOMES) + f"  wall: {wall:.1f}s")
        if not finished:
            print("stopped before all episodes finished", file=sys.stderr)
        return 0 if finished else 1
    except (ValueError, FileNotFoundError, LookupError, *runtime.SetupException) as exc:
        print(f"error: {runtime.one_line(exc)}", file=sys.stderr)
        return runtime.EXIT_CONFIG_ERROR
    finally:
        paths = [n.path for n in nodes if hasattr(n, "path") and hasattr(n, "counts")]
        runtime.close_nodes(nodes)
        runtime.close_executor(ex)
        for path in paths:
            print(f"mcap: {path}")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        defaults = C.defaults(share_of)
    except (OSError, ValueError) as exc:
        print(f"error: {runtime.one_line(exc)}", file=sys.stderr)
        return runtime.EXIT_CONFIG_ERROR
    args = build_parser(defaults).parse_args(rclpy.utilities.remove_ros_args(["x"] + argv)[1:])
    values = argument_values(args)
    try:
        runtime.init([PROG] + argv)
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return runtime.EXIT_CONFIG_ERROR
    try:
        return run(args, values)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    raise SystemExit(main())
