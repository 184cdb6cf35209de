#!/usr/bin/env python
"""ROS graph benchmark: lockstep latency and realtime sustained rate, one process vs processes.

    .venv/bin/python scripts/bench_ros.py [--ticks 300] [--rt-ticks 200] [--rates 1 2 5 10]
                                          [--layouts one-process processes] [--policy PATH]

Lockstep: per-tick latency world -> planner -> controller -> world, i.e. from the world
publishing tick k's state to it receiving the command stamped t_k (median, p99 over
``--ticks`` ticks, episodes chained). Realtime: the world steps on a wall timer at
rate_factor x 10 Hz with the latest command; for each rate factor it reports the achieved
tick rate, the command age in ticks when applied (0 = the command answers the state just
stepped from) and the ticks the world had to brake on because the command was stale
(older than command_timeout_s = 3 ticks of sim time) after the first command of the
episode. "sustained" = achieved rate within 5 % of the target and no stale command.

Layouts: ``one-process`` = world, planner and controller nodes in one
SingleThreadedExecutor (bimacppo-graph without curriculum and recorder); ``processes`` =
planner_node and controller_node as separate processes, the world in this process.
Everything goes over DDS in both. The world node is the package's, instrumented by
subclassing (timestamps only, the stepping is unchanged).

Policy: --policy, else the shipped one if present, else an untrained PPO(seed 0) export
(decisions are as cheap as a trained policy's: one forward pass).
Figures are wall-clock on whatever machine runs this; the dev box has 2 shared cores.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile
import time

import numpy as np

os.environ.setdefault("ROS_DOMAIN_ID", str(150 + os.getpid() % 80))
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)

import rclpy  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from bimacppo_interfaces import contract as I  # noqa: E402
from bimacppo_sim.ros.world_node import WorldNode  # noqa: E402

SCENARIO = dict(n_sv=2, task="straight")
TARGET_HZ = 50.0
RATE_TOLERANCE = 0.05
STARTUP_TIMEOUT_S = 60.0


class TimedWorld(WorldNode):
    """WorldNode + timestamps; chains episodes (seed + 1) so a run has as many ticks as asked."""

    def __init__(self, **kw):
        super().__init__(**kw)
        self.t_pub = {}            # stamp -> wall time of its first publication
        self.latency = []          # lockstep: s from state to its command
        self.steps = []            # realtime: (wall time, command age in ticks or None, engaged)
        self.engaged = False
        self.ep_start = 0
        self.seed = 0
        self.running = False     # set by start(): no episode before the peers are up

    def _publish_state(self):
        self.t_pub.setdefault(self.stamp_ns(), time.perf_counter())
        super()._publish_state()

    def _on_command(self, msg):
        stamp = I.stamp_to_ns(msg.header.stamp)
        if self.mode == "lockstep" and self.active and stamp == self.stamp_ns():
            self.latency.append(time.perf_counter() - self.t_pub[stamp])
        if self.mode == "realtime" and self.ep_start <= stamp <= self.stamp_ns():
            self.engaged = True
        super()._on_command(msg)
        self._chain()

    def _realtime_step(self):
        if self.active:
            cmd = self._last_cmd
            age = None if cmd is None else (self.stamp_ns() - cmd[0]) / self.dt_ns
            self.steps.append((time.perf_counter(), age, self.engaged))
        super()._realtime_step()
        self._chain()

    def _chain(self):
        if not self.active and self.running:
            self.start()

    def start(self):
        self.running = True
        self.seed += 1
        self.set_parameters([Parameter("scenario.n_sv", value=SCENARIO["n_sv"]),
                             Parameter("scenario.task", value=SCENARIO["task"]),
                             Parameter("scenario.seed", value=self.seed)])
        self.engaged = False
        self.reset_episode()
        self.ep_start = self.stamp_ns()


def make_world(mode, rate_factor):
    return TimedWorld(parameter_overrides=[
        Parameter("mode", value=mode), Parameter("autostart", value=False),
        Parameter("rate_factor", value=float(rate_factor)), Parameter("publish_markers", value=False)])


def start_peers(layout, policy, ex):
    """Planner + controller: nodes in ``ex`` or processes. Returns (nodes, procs)."""
    if layout == "one-process":
        from bimacppo_mpc.ros.controller_node import ControllerNode
        from bimacppo_planner.ros.planner_node import PlannerNode
        nodes = [PlannerNode(parameter_overrides=[Parameter("policy_path", value=policy)]), ControllerNode()]
        for n in nodes:
            ex.add_node(n)
        return nodes, []
    env = dict(os.environ)
    procs = [subprocess.Popen([sys.executable, "-m", "bimacppo_planner.ros.planner_node", "--ros-args",
                               "-p", f"policy_path:={policy}"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True),
             subprocess.Popen([sys.executable, "-m", "bimacppo_mpc.ros.controller_node"], env=env,
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)]
    return [], procs


def wait_peers(world, ex, procs, before):
    """Until planner and controller of *this* configuration are matched: their /ego/odom
    readers must be new endpoints (a stopped peer lingers in the graph for a while)."""
    t_end = time.monotonic() + STARTUP_TIMEOUT_S
    while time.monotonic() < t_end:
        new = [i for i in world.get_subscriptions_info_by_topic(I.TOPIC_EGO_ODOM)
               if bytes(i.endpoint_gid) not in before]
        if {"planner", "controller"} <= {i.node_name for i in new} and world.pub_odom.get_subscription_count() >= 2:
            break
        for p in procs:
            if p.poll() is not None:
                raise RuntimeError(f"peer exited: {p.stderr.read()}")
        ex.spin_once(timeout_sec=0.05)
    else:
        raise RuntimeError("planner/controller did not come up")
    t_end = time.monotonic() + 0.5  # let the matches settle on the readers' side too
    while time.monotonic() < t_end:
        ex.spin_once(timeout_sec=0.05)


def stop_peers(nodes, procs):
    for n in nodes:
        n.destroy_node()
    for p in procs:
        p.terminate()
    for p in procs:
        try:
            p.wait(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run_config(layout, policy, mode, rate_factor, n_ticks):
    ex = SingleThreadedExecutor()
    world = make_world(mode, rate_factor)
    ex.add_node(world)
    before = {bytes(i.endpoint_gid) for i in world.get_subscriptions_info_by_topic(I.TOPIC_EGO_ODOM)}
    nodes, procs = start_peers(layout, policy, ex)
    try:
        wait_peers(world, ex, procs, before)
        world.start()
        count = (lambda: len(world.latency)) if mode == "lockstep" else (lambda: len(world.steps))
        t_end = time.monotonic() + max(60.0, 5.0 * n_ticks / (10.0 * rate_factor))
        while count() < n_ticks and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
        world.running = False
        if count() < n_ticks:
            print(f"  warning: {layout} {mode} x{rate_factor}: only {count()} of {n_ticks} ticks", file=sys.stderr)
        return (world.latency if mode == "lockstep" else world.steps)[:n_ticks], world.results
    finally:
        stop_peers(nodes, procs)
        ex.remove_node(world)
        world.destroy_node()


def lockstep_figures(lat):
    a = np.asarray(lat) * 1e3
    return {"ticks": len(a), "median_ms": float(np.median(a)), "p99_ms": float(np.percentile(a, 99)),
            "max_ms": float(a.max()), "ticks_per_s": float(1e3 / a.mean())}


def realtime_figures(steps, rate_factor):
    t = np.array([s[0] for s in steps])
    ages = [s[1] for s in steps if s[2] and s[1] is not None]
    engaged = [s for s in steps if s[2]]
    stale = sum(1 for s in engaged if s[1] is None or s[1] * 0.1 > 0.3 + 1e-9)
    target = 10.0 * rate_factor
    achieved = float((len(t) - 1) / (t[-1] - t[0])) if len(t) > 1 else 0.0
    return {"target_hz": target, "achieved_hz": achieved,
            "age_median": float(np.median(ages)) if ages else float("nan"),
            "age_max": float(max(ages)) if ages else float("nan"),
            "stale": stale, "engaged": len(engaged), "ticks": len(steps),
            "sustained": bool(achieved >= (1 - RATE_TOLERANCE) * target and stale == 0 and len(engaged) > 0)}


def pick_policy(arg, tmp):
    if arg:
        return arg, arg
    from bimacppo_planner.agent import shipped_policy_path
    shipped = shipped_policy_path()
    if shipped.is_file():
        return str(shipped), "shipped policy"
    from bimacppo_learning.checkpoint import export_policy
    from bimacppo_learning.ppo import PPO
    path = os.path.join(tmp, "untrained.pt")
    export_policy(PPO(16, (5, 5, 3), seed=0), path)
    return path, "untrained PPO(seed 0) export (no shipped policy yet)"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--ticks", type=int, default=300, help="lockstep ticks per layout (>= 300 asked)")
    ap.add_argument("--rt-ticks", type=int, default=200, help="realtime ticks per rate factor")
    ap.add_argument("--rates", type=float, nargs="+", default=[1.0, 2.0, 5.0, 10.0])
    ap.add_argument("--layouts", nargs="+", default=["one-process", "processes"],
                    choices=["one-process", "processes"])
    ap.add_argument("--policy", default="")
    args = ap.parse_args(argv)
    if args.ticks < 1 or args.rt_ticks < 2 or any(r <= 0 for r in args.rates):
        ap.error("--ticks >= 1, --rt-ticks >= 2 and rates > 0 required")
    rclpy.init(args=["bench_ros"])
    tmp = tempfile.mkdtemp(prefix="bench_ros_")
    try:
        policy, what = pick_policy(args.policy, tmp)
        print(f"# bench_ros: {platform.node()}, {os.cpu_count()} CPUs, python {platform.python_version()}, "
              f"policy: {what}; scenario n_sv={SCENARIO['n_sv']} task={SCENARIO['task']}, seeds 1, 2, ...")
        lock, rt = {}, {}
        for layout in args.layouts:
            lat, res = run_config(layout, policy, "lockstep", 1.0, args.ticks)
            lock[layout] = lockstep_figures(lat)
            print(f"  {layout:12s} lockstep: {lock[layout]}  episodes: {[r.outcome for r in res]}", flush=True)
            for rf in args.rates:
                steps, _ = run_config(layout, policy, "realtime", rf, args.rt_ticks)
                rt[(layout, rf)] = realtime_figures(steps, rf)
                print(f"  {layout:12s} realtime x{rf:g}: {rt[(layout, rf)]}", flush=True)
        print_table(args, lock, rt)
    finally:
        rclpy.try_shutdown()
    return 0


def print_table(args, lock, rt):
    lay = args.layouts
    w = 24
    print()
    print("| lockstep (world -> planner -> controller -> world) | " + " | ".join(lay) + " |")
    print("|---|" + "---|" * len(lay))
    for key, label in (("ticks", "ticks"), ("median_ms", "latency median (ms)"), ("p99_ms", "latency p99 (ms)"),
                       ("max_ms", "latency max (ms)"), ("ticks_per_s", "lockstep ticks/s (1 / mean)")):
        vals = [lock[l][key] for l in lay]
        print(f"| {label:{w}s} | " + " | ".join(f"{v:.0f}" if key == "ticks" else f"{v:.2f}" for v in vals) + " |")
    print()
    print("| realtime rate factor (target Hz) | " + " | ".join(
        f"{l}: achieved Hz / age med, max (ticks) / stale of engaged" for l in lay) + " |")
    print("|---|" + "---|" * len(lay))
    for rf in args.rates:
        cells = []
        for l in lay:
            f = rt[(l, rf)]
            cells.append(f"{f['achieved_hz']:.1f} / {f['age_median']:.0f}, {f['age_max']:.0f} / "
                         f"{f['stale']} of {f['engaged']}" + (" ✓" if f["sustained"] else " ✗"))
        print(f"| x{rf:g} ({10 * rf:.0f} Hz) | " + " | ".join(cells) + " |")
    print()
    for l in lay:
        ok = [rf for rf in args.rates if rt[(l, rf)]["sustained"]]
        if not ok:
            print(f"{l}: none of the rate factors tried was sustained without stale commands")
            continue
        best = max(ok) * 10
        print(f"{l}: highest rate tried that was sustained without stale commands: {best:.0f} Hz "
              f"(target >= {TARGET_HZ:.0f} Hz: {'met' if best >= TARGET_HZ else 'NOT met'})")

if __name__ == "__main__":
    raise SystemExit(main())
