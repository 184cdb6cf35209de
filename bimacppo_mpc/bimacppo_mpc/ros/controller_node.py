"""Controller node: the NMPC (``make_controller``) between /planner/reference and /control/command.

For each reference (stamp s) it takes the ego state of the same stamp, solves eq.
(32)-(33) and publishes the command stamped s: point 0 is the input to apply, further
points the planned horizon. A repeated reference stamp (the lockstep world re-sent a
tick) is answered from a cache, so the MPC's warm start and u_prev advance exactly once
per tick, as in the in-process loop. The MPC is reset (warm start, u_prev = 0) when a new
goal starts an episode, as ``IntersectionEnv.reset`` does.

Watchdog: if no reference or no state arrived for ``watchdog_timeout_s`` of ROS time
(sim time when ``use_sim_time``), a safe-stop command (a_min of the MPC bounds, steering
held) is published every check. In lockstep, sim time only advances when the loop runs,
so the watchdog cannot inject commands there; it acts in realtime and deployment.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np
from rclpy.node import Node

from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_sim.ros import interfaces as I
from bimacppo_sim.ros.runtime import run_single


class ControllerNode(Node):
    """Thin adapter over ``MPCController.solve``."""

    def __init__(self, **kwargs) -> None:
        super().__init__(I.CONTROLLER_NODE, **kwargs)
        self.declare_parameter("solver", "fast")
        self.declare_parameter("config", "")
        self.declare_parameter("watchdog_timeout_s", 0.5)
        self.declare_parameter("publish_horizon", True)
        self.declare_parameter("cache_size", 64)
        g = lambda n: self.get_parameter(n).value  # noqa: E731
        self.cfg = MPCConfig.load(g("config")) if g("config") else MPCConfig.load()
        self.ctrl = make_controller(self.cfg, solver=g("solver"))
        self.timeout_ns = int(float(g("watchdog_timeout_s")) * I.NS_PER_S)
        self.horizon = bool(g("publish_horizon"))
        self.cache_size = int(g("cache_size"))
        if self.timeout_ns <= 0 or self.cache_size <= 0:
            raise ValueError("controller: watchdog_timeout_s and cache_size must be > 0")
        self._warm_up()
        self.gate = I.EpisodeGate()
        self.u_prev = np.zeros(2)
        self.states: OrderedDict = OrderedDict()     # stamp -> x0
        self.pending: OrderedDict = OrderedDict()    # stamp -> x_ref waiting for its state / goal
        self.answers: OrderedDict = OrderedDict()    # stamp -> JointTrajectory already sent
        self.solves = 0
        self.failures = 0
        self._last_ref = None
        self._last_state = None
        self.pub = self.create_publisher(I.JointTrajectory, I.TOPIC_COMMAND, I.STATE_QOS)
        # goal/result first: when several are ready at once, the executor serves them first
        self.create_subscription(I.PoseStamped, I.TOPIC_GOAL, self._on_goal, I.LATCHED_QOS)
        self.create_subscription(I.DiagnosticStatus, I.TOPIC_RESULT, self._on_result, I.RESULT_QOS)
        self.create_subscription(I.Odometry, I.TOPIC_EGO_ODOM, self._on_odom, I.STATE_QOS)
        self.create_subscription(I.Odometry, I.TOPIC_REFERENCE, self._on_reference, I.STATE_QOS)
        self.create_timer(self.timeout_ns / I.NS_PER_S / 2.0, self._watchdog)

    def _warm_up(self) -> None:
        """One throw-away solve before any subscription exists.

        The first solve loads / compiles the numba kernels (0.3 s measured on the dev box,
        more under load). Inside the first tick that stalls the loop: a lockstep world
        just waits, but an open-loop source (realtime world, MCAP player) runs on and the
        keep_last queues drop the ticks published meanwhile (measured with the player at
        100 ticks/s: ticks 2..68 of the recording lost). The solver state is reset after.
        """
        self.ctrl.solve(np.array([0.0, 0.0, 1.0, 0.0]), np.array([5.0, 0.0, 1.0, 0.0]), np.zeros(2))
        self.ctrl.reset()

    def _bounded(self, d: OrderedDict) -> None:
        while len(d) > self.cache_size:
            d.popitem(last=False)

    def _now(self) -> int:
        return self.get_clock().now().nanoseconds

    def _on_goal(self, msg) -> None:
        try:
            goal = I.pose_to_goal(msg)
        except I.MessageError as exc:
            self.get_logger().warning(f"ignored goal: {exc}")
            return
        self.gate.on_goal(I.stamp_to_ns(msg.header.stamp), goal)
        self._process()

    def _on_result(self, msg) -> None:
        try:
            res = I.status_to_result(msg)
        except I.MessageError:
            return
        self.gate.on_result(res.stamp_ns)

    def _on_odom(self, msg) -> None:
        try:
            x = I.odometry_to_state(msg)
        except I.MessageError as exc:
            self.get_logger().warning(f"ignored state: {exc}")
            return
        self.states[I.stamp_to_ns(msg.header.stamp)] = x
        self._bounded(self.states)
        self._last_state = self._now()
        self._process()

    def _on_reference(self, msg) -> None:
        try:
            x_ref = I.odometry_to_reference(msg)
        except I.MessageError as exc:
            self.get_logger().warning(f"ignored reference: {exc}")
            return
        stamp = I.stamp_to_ns(msg.header.stamp)
        self._last_ref = self._now()
        if stamp in self.answers:
            self.pub.publish(self.answers[stamp])
            return
        self.pending[stamp] = x_ref
        self._bounded(self.pending)
        self._process()

    def _process(self) -> None:
        for stamp in list(self.pending):
            kind = self.gate.classify(stamp)
            if kind == "stale":
                del self.pending[stamp]
                continue
            if kind == "wait" or stamp not in self.states:
                continue
            x_ref = self.pending.pop(stamp)
            if self.gate.new_episode():
                self.ctrl.reset()
                self.u_prev = np.zeros(2)
            sol = self.ctrl.solve(self.states[stamp], x_ref, self.u_prev)
            self.solves += 1
            if not sol.ok:
                self.failures += 1
                self.get_logger().warning(f"MPC fallback at {stamp} ns: {sol.status}", throttle_duration_sec=1.0)
            self.u_prev = np.asarray(sol.u, dtype=float)
            cmd = I.command_to_trajectory(sol.u, stamp, sol.U if self.horizon else None, self.cfg.dt)
            self.answers[stamp] = cmd
            self._bounded(self.answers)
            self.pub.publish(cmd)

    def _watchdog(self) -> None:
        if self._last_ref is None:
            return  # never engaged: nothing to stop
        now = self._now()
        if now - self._last_ref > self.timeout_ns or now - (self._last_state or 0) > self.timeout_ns:
            u = np.array([self.cfg.a_min, float(self.u_prev[1])])
            self.pub.publish(I.command_to_trajectory(u, max(now, 0)))
            self.get_logger().warning("no fresh reference/state: safe stop", throttle_duration_sec=2.0)


def main(argv=None) -> int:
    def make(args):
        if args:
            raise ValueError(f"controller_node takes no positional arguments (got {args})")
        return ControllerNode()
    return run_single(make, argv)


if __name__ == "__main__":
    raise SystemExit(main())
