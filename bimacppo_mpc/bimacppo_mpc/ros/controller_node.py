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

Faults (docs/faults.md): every callback is ``runtime.guarded`` (a bad message is dropped
with a throttled warning, the node never dies of one); which input is answered, repeated,
kept or dropped is the tick protocol's verdict (``tick_protocol.TickProtocol``, its table in
docs/interfaces.md), shared with the planner. A solve that yields a
non-finite input is answered with the safe stop instead.
"""
from __future__ import annotations

from collections import OrderedDict

import numpy as np
from rclpy.node import Node

from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_interfaces import contract as I
from bimacppo_ros_common.params import declare, param_file
from bimacppo_ros_common.runtime import guarded, run_single
from bimacppo_ros_common.tick_protocol import MAX_STAMP_JUMP_S, REFUSED, TickProtocol, Verdict

SOLVERS = ("fast", "ipopt")


class ControllerNode(Node):
    """Thin adapter over ``MPCController.solve``."""

    def __init__(self, **kwargs) -> None:
        super().__init__(I.CONTROLLER_NODE, **kwargs)
        name = "controller"
        solver = declare(self, "solver", "fast", "NMPC solver", choices=SOLVERS)
        config = declare(self, "config", "", "MPC config YAML overlaying the packaged mpc.yaml; empty: packaged")
        cfg_path = param_file(config, "config", name) if config else None
        self.cfg = MPCConfig.load(cfg_path)
        self.ctrl = make_controller(self.cfg, solver=solver)
        self.timeout_ns = int(declare(self, "watchdog_timeout_s", 0.5, "no reference for this long (ROS time) "
                                      "means a safe stop", lo=0.01, hi=60.0) * I.NS_PER_S)
        self.horizon = declare(self, "publish_horizon", True, "send the MPC horizon as points 1..N-1 of the command")
        cache_size = declare(self, "cache_size", 64, "answers kept per stamp (re-sent ticks are answered from it)",
                             lo=1, hi=100_000)
        jump_ns = int(declare(self, "max_stamp_jump_s", MAX_STAMP_JUMP_S, "a stamp further ahead of the newest "
                              "answered tick is a jump (docs/interfaces.md, tick protocol)",
                              lo=0.1, hi=3600.0) * I.NS_PER_S)
        # answers: stamp -> JointTrajectory sent
        self.protocol = TickProtocol(cache_size, jump_ns, log=lambda level, m: getattr(self.get_logger(), level)(m),
                                     on_restart=self._clear_tick_caches)
        self.dropped: dict = {}          # topic -> messages dropped (bad content or stamp)
        self._warm_up()
        self.u_prev = np.zeros(2)
        self.states: OrderedDict = OrderedDict()     # stamp -> x0
        self.pending: OrderedDict = OrderedDict()    # stamp -> x_ref waiting for its state / goal
        self.solves = 0
        self.failures = 0
        self._last_ref = None
        self._last_state = None
        self.pub = self.create_publisher(I.JointTrajectory, I.TOPIC_COMMAND, I.STATE_QOS)
        # goal/result first: when several are ready at once, the executor serves them first
        sub = lambda typ, topic, fn, qos: self.create_subscription(  # noqa: E731
            typ, topic, guarded(self, topic, fn, self.dropped), qos)
        sub(I.PoseStamped, I.TOPIC_GOAL, self._on_goal, I.LATCHED_QOS)
        sub(I.DiagnosticStatus, I.TOPIC_RESULT, self._on_result, I.RESULT_QOS)
        sub(I.Odometry, I.TOPIC_EGO_ODOM, self._on_odom, I.STATE_QOS)
        sub(I.Odometry, I.TOPIC_REFERENCE, self._on_reference, I.STATE_QOS)
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

    def _now(self) -> int:
        return self.get_clock().now().nanoseconds

    def _clear_tick_caches(self) -> None:
        self.states.clear(), self.pending.clear()

    def _on_goal(self, msg) -> None:
        if self.protocol.on_goal(I.stamp_to_ns(msg.header.stamp), I.pose_to_goal(msg)) in REFUSED:
            raise I.MessageError(self.protocol.reason)
        self._process()

    def _on_result(self, msg) -> None:
        res = I.status_to_result(msg)
        if self.protocol.on_result(res.stamp_ns) in REFUSED:
            raise I.MessageError(self.protocol.reason)

    def _on_odom(self, msg) -> None:
        x = I.odometry_to_state(msg)
        stamp = I.stamp_to_ns(msg.header.stamp)
        if self.protocol.on_state(stamp, x) in REFUSED:
            raise I.MessageError(self.protocol.reason)
        self.states[stamp] = x
        self.protocol.bound(self.states)
        self._last_state = self._now()
        self._process()

    def _on_reference(self, msg) -> None:
        x_ref = I.odometry_to_reference(msg)
        stamp = I.stamp_to_ns(msg.header.stamp)
        verdict = self.protocol.on_input(stamp, "reference")
        if verdict is Verdict.REPEAT:
            self._last_ref = self._now()
            self.pub.publish(self.protocol.cached(stamp))
            return
        if verdict in REFUSED:
            raise I.MessageError(self.protocol.reason)
        self._last_ref = self._now()
        self.pending[stamp] = x_ref
        self.protocol.bound(self.pending)
        self._process()

    def _process(self) -> None:
        p = self.protocol
        for stamp in list(self.pending):
            kind = p.classify(stamp)
            if kind is Verdict.STALE:
                del self.pending[stamp]
                continue
            if kind is Verdict.WAIT or stamp not in self.states:
                continue
            x_ref = self.pending.pop(stamp)
            if p.start_episode():
                self.ctrl.reset()
                self.u_prev = np.zeros(2)
            if not p.current(stamp):
                continue  # a newer reference answered meanwhile
            try:
                sol = self.ctrl.solve(self.states[stamp], x_ref, self.u_prev)
                u = np.asarray(sol.u, dtype=float)
                ok = u.shape == (2,) and bool(np.all(np.isfinite(u)))  # not ok: the core's own fallback
            except Exception as exc:  # noqa: BLE001 - a solver failure must not kill the node
                sol, ok = None, False
                self.get_logger().error(f"MPC solve raised at {stamp} ns: {type(exc).__name__}: {exc}",
                                        throttle_duration_sec=1.0)
            self.solves += 1
            if sol is not None and not sol.ok:
                self.failures += 1
                self.get_logger().warning(f"MPC fallback at {stamp} ns: {sol.status}", throttle_duration_sec=1.0)
            if not ok:
                # non-finite input or the solver raised: the safe stop, never a NaN on the wire
                u = np.array([self.cfg.a_min, float(self.u_prev[1]) if np.isfinite(self.u_prev[1]) else 0.0])
                horizon = None
            else:
                horizon = np.asarray(sol.U, dtype=float) if self.horizon else None
                if horizon is not None and not np.all(np.isfinite(horizon)):
                    horizon = None
            self.u_prev = u
            cmd = I.command_to_trajectory(u, stamp, horizon, self.cfg.dt)
            p.answered(stamp, cmd, self.states[stamp])
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
