"""The demo: world, planner, controller, curriculum and the MCAP recorder in one process.

    bimacppo-graph --episodes 5 --output run.mcap [--policy PATH] [--mode lockstep|realtime]

Executor: ``SingleThreadedExecutor``. The nodes are Python and CPU-bound, so threads
would only contend for the GIL; the lockstep loop is sequential by construction
(state -> reference -> command -> step); and one thread makes callback order, hence
a run, reproducible. Everything still goes through DDS exactly as across processes,
so this is the same graph as ``ros2 run`` of each node (docs/ros.md).
Prints success / collision / timeout counts and the MCAP path at the end.
"""
from __future__ import annotations

import argparse
import sys
import time
from collections import Counter

import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter

from bimacppo_sim.ros import runtime


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="bimacppo-graph", description=__doc__.split("\n\n")[0])
    ap.add_argument("--episodes", type=int, default=3, help="episodes to run (curriculum stops after)")
    ap.add_argument("--scheduler", default="bimab", help="bimab | fixed | random | manual | rd")
    ap.add_argument("--seed", type=int, default=0, help="scheduler seed")
    ap.add_argument("--seed-base", type=int, default=0, help="scenario seed of the first episode")
    ap.add_argument("--policy", default="", help="checkpoint (default: the shipped policy)")
    ap.add_argument("--planner-class", default="", help="module:Class with load/reset/step (testing)")
    ap.add_argument("--map", default="dual_lane_4way")
    ap.add_argument("--mode", default="lockstep", choices=("lockstep", "realtime"))
    ap.add_argument("--rate-factor", type=float, default=1.0, help="realtime: sim s per wall s")
    ap.add_argument("--solver", default="fast", help="MPC solver: fast | ipopt")
    ap.add_argument("--output", default="", help="MCAP path (default: bimacppo_<time>.mcap)")
    ap.add_argument("--no-record", action="store_true")
    ap.add_argument("--timeout", type=float, default=0.0, help="wall-clock limit in s (0 = none)")
    ap.add_argument("--live-view", nargs="?", type=int, const=None, default=False, metavar="PORT",
                    help="serve the graph to Foxglove on ws://127.0.0.1:PORT (default port 8765; "
                         "bimacppo_viz, docs/live-view.md)")
    return ap


def run(args) -> int:
    from bimacppo_curriculum.ros.curriculum_node import CurriculumNode
    from bimacppo_mpc.ros.controller_node import ControllerNode
    from bimacppo_sim.ros.recorder import McapRecorder
    from bimacppo_sim.ros.world_node import WorldNode

    from .planner_node import PlannerNode

    P = Parameter
    nodes = []
    ex = SingleThreadedExecutor()
    stop = runtime.StopFlag().install()
    try:
        rec = None
        if not args.no_record:
            rec = McapRecorder(output=args.output or None)
            nodes.append(rec)
        world = WorldNode(parameter_overrides=[
            P("map_id", value=args.map), P("mode", value=args.mode), P("autostart", value=False),
            P("rate_factor", value=args.rate_factor)])
        planner_params = [P("map_id", value=args.map), P("policy_path", value=args.policy)]
        if args.planner_class:
            planner_params.append(P("planner_class", value=args.planner_class))
        planner = PlannerNode(parameter_overrides=planner_params)
        ctrl = ControllerNode(parameter_overrides=[P("solver", value=args.solver)])
        cur = CurriculumNode(parameter_overrides=[
            P("scheduler", value=args.scheduler), P("seed", value=args.seed),
            P("episodes", value=args.episodes), P("seed_base", value=args.seed_base)])
        nodes += [world, planner, ctrl, cur]
        if args.live_view is not False:   # the flag alone: the node's default port
            try:
                from bimacppo_viz.ros.live_view import LiveViewNode
            except ImportError as exc:
                raise LookupError(f"--live-view needs bimacppo_viz and foxglove-sdk (scripts/install.sh "
                                  f"installs both): {exc}") from None
            nodes.append(LiveViewNode(parameter_overrides=[P("map_id", value=args.map)] + (
                [] if args.live_view is None else [P("port", value=args.live_view)])))
        for n in nodes:
            ex.add_node(n)
        if rec is not None:
            rec.discover()  # subscribe before the first episode starts
        t0 = time.monotonic()
        finished = runtime.spin(ex, stop, done=lambda: cur.done,
                                timeout_s=args.timeout if args.timeout > 0 else None)
        runtime.drain(ex)
        wall = time.monotonic() - t0
        counts = Counter(r[3] for r in cur.results)
        n = max(len(cur.results), 1)
        print(f"episodes: {len(cur.results)}  " + "  ".join(
            f"{k}: {counts.get(k, 0)} ({100.0 * counts.get(k, 0) / n:.0f}%)"
            for k in ("success", "collision", "timeout")) + f"  wall: {wall:.1f}s")
        if not finished:
            print("stopped before all episodes finished", file=sys.stderr)
        return 0 if finished else 1
    except (ValueError, FileNotFoundError, LookupError, *runtime.SetupException) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return runtime.EXIT_CONFIG_ERROR
    finally:
        paths = [n.path for n in nodes if hasattr(n, "path") and hasattr(n, "counts")]
        runtime.close_nodes(nodes)
        for path in paths:
            print(f"mcap: {path}")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(rclpy.utilities.remove_ros_args(["x"] + argv)[1:])
    try:
        runtime.init(["bimacppo-graph"] + argv)
    except runtime.ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return runtime.EXIT_CONFIG_ERROR
    try:
        return run(args)
    finally:
        rclpy.try_shutdown()


if __name__ == "__main__":
    raise SystemExit(main())
