"""World node: ``bimacppo_sim.World`` behind the topics of docs/interfaces.md.

Two clocking modes (parameter ``mode``):

* ``lockstep`` (deterministic): after publishing tick k's state the world waits for the
  /control/command whose header.stamp equals tick k's stamp, then steps. If that command
  does not come within ``resend_period_s`` (wall), tick k's messages are published again
  (same stamp; the planner and controller answer repeats from their caches), so a node
  that joined late or a lost sample never deadlocks the loop. After ``resend_warn_after``
  re-sends of one tick without its command the world warns once for that tick (with the
  count), and says after how many re-sends it was answered.
* ``realtime``: a wall timer steps every dt / ``rate_factor`` with the latest command; a
  command older than ``command_timeout_s`` (sim time) or none at all means brake
  (a_min of the vehicle config) with the steering held (a warning says so). A command
  stamped after the current tick answers no state and is dropped.

While an episode runs, its goal is re-published every ``goal_resend_period_s`` (wall;
same stamp, so receivers see a repeat, not a new episode). /goal_pose is latched, but a
late-joining reader does not always get the latched sample: with Fast DDS, a planner or
controller restarted after a SIGKILL sometimes never received it and then waited for a
goal forever (fault suite). The re-send bounds that wait.

Sim time only grows, also across resets (a reset advances it by one tick) and across runs:
a run starts one tick after every stamp an earlier run in the same DDS domain reserved
(``bimacppo_ros_common.run_clock``; parameter ``clock_file``, default
``$ROS_HOME/bimacppo/world_clock_domain<ROS_DOMAIN_ID>``, ``none``: every run starts at one
tick). So every published state has a unique stamp, /clock never jumps back, and a goal's
stamp identifies its episode even when the world is restarted within an episode.

Faults (docs/faults.md): the command callback is ``runtime.guarded`` (a malformed command is
dropped with a throttled warning); commands are clipped to the vehicle's limits by
``World.step``; start-up parameters are checked (ranges, a ``map_id`` path must be a
readable, valid map file) and a problem is one ``error:`` line with exit code 2.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Optional

import numpy as np
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rosgraph_msgs.msg import Clock as ClockMsg
from std_srvs.srv import Trigger

from bimacppo_common.conventions import TASKS
from bimacppo_interfaces import contract as I
from bimacppo_ros_common.params import ConfigError, declare
from bimacppo_ros_common.run_clock import NO_FILE, RunClock, default_clock_file
from bimacppo_ros_common.runtime import guarded, one_line, run_single
from bimacppo_sim import Scenario, World, draw_n_slow, load_map

MODES = ("lockstep", "realtime")
SLOW_SVS_MAX = 16      # the parameter's range; draw_n_slow caps the draw at the episode's N_sv anyway
SCENARIO_PARAMS = ("scenario.n_sv", "scenario.task", "scenario.seed", "scenario.slow_svs")


class WorldNode(Node):
    """Simulator adapter; all dynamics, SV behaviour and outcomes come from ``World``."""

    def __init__(self, **kwargs) -> None:
        super().__init__(I.WORLD_NODE, **kwargs)
        map_id = declare(self, "map_id", "dual_lane_4way", "map: a packaged id or a map YAML path")
        self.mode = declare(self, "mode", "lockstep", "lockstep (deterministic) or realtime (wall timer)",
                            choices=MODES)
        autostart = declare(self, "autostart", True, "start the scenario at start-up (false when a curriculum "
                                                     "drives)")
        declare(self, "scenario.n_sv", 0, "N_sv of the next episode (read at each reset)", read_only=False)
        declare(self, "scenario.task", "straight", "task of the next episode (read at each reset)",
                choices=TASKS, read_only=False)
        declare(self, "scenario.seed", 0, "scenario seed of the next episode (read at each reset)", read_only=False)
        declare(self, "scenario.slow_svs", 0, "at most this many SVs drive slowly, their number drawn from the "
                "scenario seed as in training and evaluation's --slow-svs (the overtaking protocol: 2 on "
                "three_lane_straight); 0 = none (read at each reset)", lo=0, hi=SLOW_SVS_MAX, read_only=False)
        self.rate_factor = declare(self, "rate_factor", 1.0, "realtime: sim seconds per wall second",
                                   lo=0.01, hi=1000.0)
        self.command_timeout_ns = int(declare(self, "command_timeout_s", 0.3, "realtime: a command older than "
                                              "this (sim s) or none means brake", lo=0.01, hi=60.0) * I.NS_PER_S)
        self.resend_period = declare(self, "resend_period_s", 0.5, "lockstep: re-publish the current tick when "
                                     "no command came for this long (wall s)", lo=0.01, hi=60.0)
        self.resend_warn_after = declare(self, "resend_warn_after", 10, "lockstep: warn once when one tick was "
                                         "re-sent this many times", lo=1, hi=1_000_000)
        self.goal_resend_period = declare(self, "goal_resend_period_s", 1.0, "re-publish the running episode's "
                                          "goal this often (wall s; 0 = never)", lo=0.0, hi=3600.0)
        self.markers_on = declare(self, "publish_markers", True, "publish /objects/markers")
        clock_file = declare(self, "clock_file", "", "run-clock lease file: empty = $ROS_HOME/bimacppo/"
                                                     f"world_clock_domain<id>; {NO_FILE} = each run from one tick")
        try:
            road = load_map(map_id)
        except Exception as exc:  # noqa: BLE001 - YAML syntax, missing keys, wrong types: all user errors
            raise ConfigError(f"world: parameter map_id {map_id!r}: {type(exc).__name__}: "
                              f"{one_line(exc)}") from None
        # the tasks the map offers, in TASKS order: a client (the curriculum) reads them and runs
        # each arm's task through conventions.task_on_map; the world refuses any other task
        self.tasks = road.tasks
        offered = declare(self, "map_tasks", list(self.tasks), "tasks the map offers (set from map_id; a "
                                                                 "curriculum reads it)")
        if tuple(offered) != self.tasks:
            raise ConfigError(f"world: parameter map_tasks comes from the map ({', '.join(self.tasks)}); "
                              f"it cannot be set (got {list(offered)})")
        self.dropped: dict = {}
        self.world = World(road)
        self.frame = road.frame        # the map file's pose: the core runs in the map's own frame
        self.dt_ns = int(round(self.world.dt * I.NS_PER_S))
        veh = self.world.cfg.vehicle
        self.brake = float(veh.a_min)
        self.style = I.MarkerStyle(length=veh.length, width=veh.width)
        self._check_scenario(self._scenario_params())
        self.add_on_set_parameters_callback(self._on_set_parameters)

        self.pub_clock = self.create_publisher(ClockMsg, I.TOPIC_CLOCK, I.CLOCK_QOS)
        self.pub_odom = self.create_publisher(I.Odometry, I.TOPIC_EGO_ODOM, I.STATE_QOS)
        self.pub_objects = self.create_publisher(I.MultiDOFJointTrajectory, I.TOPIC_OBJECTS, I.STATE_QOS)
        self.pub_markers = self.create_publisher(I.MarkerArray, I.TOPIC_MARKERS, I.MARKER_QOS)
        self.pub_goal = self.create_publisher(I.PoseStamped, I.TOPIC_GOAL, I.LATCHED_QOS)
        self.pub_result = self.create_publisher(I.DiagnosticStatus, I.TOPIC_RESULT, I.RESULT_QOS)
        self.create_subscription(I.JointTrajectory, I.TOPIC_COMMAND,
                                 guarded(self, I.TOPIC_COMMAND, self._on_command, self.dropped), I.STATE_QOS)
        self.create_service(Trigger, "~/reset", self._on_reset)

        self.clock = RunClock(self.dt_ns, None if clock_file == NO_FILE else
                              (clock_file or default_clock_file()),
                              warning=lambda m: self.get_logger().warning(m))
        if self.clock.first_tick > 1:
            self.get_logger().info(f"clock starts at {self.clock.first_tick * self.dt_ns / I.NS_PER_S:.1f} s, "
                                   f"after the earlier runs' ({self.clock.path})")
        self.active = False            # an episode is running
        self.episodes = 0
        self.results = []              # EpisodeResult of every finished episode (for in-process use)
        self.trajectory = []           # (stamp_ns, ego) of the current episode
        self._last_cmd: Optional[tuple] = None   # (stamp_ns, u)
        self._last_pub = 0.0
        self._resends = 0              # re-sends of the current tick
        self._goal_msg = None          # the current episode's /goal_pose (re-sent while active)
        self._last_goal_pub = 0.0
        self._delta_hold = 0.0
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        if self.mode == "lockstep":
            self.create_timer(max(self.resend_period, 0.01), self._resend, clock=steady)
        else:
            self.create_timer(self.world.dt / self.rate_factor, self._realtime_step, clock=steady)
        if self.goal_resend_period > 0.0:
            self.create_timer(self.goal_resend_period / 2.0, self._resend_goal, clock=steady)
        if autostart:
            self.reset_episode()

    # ------------------------------------------------------------------ parameters
    def _scenario_params(self):
        return tuple(self.get_parameter(n).value for n in SCENARIO_PARAMS)

    def _check_scenario(self, params) -> Scenario:
        n_sv, task, seed, slow_svs = params
        if task not in TASKS:
            raise ValueError(f"world: scenario.task must be one of {TASKS}, got {task!r}")
        if task not in self.tasks:
            raise ValueError(f"world: scenario.task {task!r} is not available on map {self.world.road.id!r} "
                             f"(map_tasks: {', '.join(self.tasks)})")
        if not isinstance(n_sv, int) or not 0 <= n_sv <= self.world.max_sv:
            raise ValueError(f"world: scenario.n_sv must be an integer in 0..{self.world.max_sv}, got {n_sv!r}")
        sc = Scenario(n_sv=n_sv, task=task, seed=seed)     # checks the seed before it is drawn from
        return dataclasses.replace(sc, n_slow=draw_n_slow(seed, n_sv, slow_svs))

    def _on_set_parameters(self, params) -> SetParametersResult:
        """Run-time changes are applied or refused with a reason, never accepted and ignored:
        the scenario.* parameters are read at each reset (how the curriculum picks episodes) and
        checked here; every other parameter is read-only (read once at start-up), which rclpy
        refuses before this callback."""
        cur = dict(zip(SCENARIO_PARAMS, self._scenario_params()))
        cur.update({prm.name: prm.value for prm in params if prm.name in cur})
        try:
            self._check_scenario(tuple(cur.values()))
        except (ValueError, TypeError) as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    # ------------------------------------------------------------------ episode
    def stamp_ns(self) -> int:
        return self.clock.stamp_ns()

    def reset_episode(self) -> Scenario:
        """Start the scenario in the parameters (also what /world/reset does)."""
        sc = self._check_scenario(self._scenario_params())
        self.world.reset(sc)
        self.clock.advance()
        self.active = True
        self.trajectory = []
        self._last_cmd = None
        self._resends = 0
        self._delta_hold = 0.0
        self._goal_msg = I.goal_to_pose(self.frame.poses_to_world(self.world.goal), self.stamp_ns())
        self.pub_goal.publish(self._goal_msg)
        self._last_goal_pub = time.monotonic()
        self._publish_state()
        return sc

    def _on_reset(self, _req, resp):
        try:
            sc = self.reset_episode()
        except (ValueError, TypeError) as exc:
            resp.success, resp.message = False, str(exc)
            return resp
        resp.success = True
        resp.message = f"n_sv={sc.n_sv} task={sc.task} seed={sc.seed} n_slow={sc.n_slow} stamp_ns={self.stamp_ns()}"
        return resp

    def _publish_state(self) -> None:
        stamp = self.stamp_ns()
        w = self.world
        f = self.frame
        ego, svs = f.states_to_world(w.ego), f.states_to_world(np.asarray(w.sv_states()).reshape(-1, 4))
        if not self.trajectory or self.trajectory[-1][0] != stamp:
            self.trajectory.append((stamp, ego.copy()))
        self.pub_clock.publish(ClockMsg(clock=I.ns_to_stamp(stamp)))
        self.pub_odom.publish(I.state_to_odometry(ego, stamp))
        self.pub_objects.publish(I.svs_to_objects(w.sv_ids, svs, stamp))
        if self.markers_on:
            route = None if w.route is None else f.poses_to_world(np.asarray(w.route)[:, :3])
            self.pub_markers.publish(I.world_markers(ego, svs, f.poses_to_world(w.goal), route, stamp,
                                                     self.style))
        self._last_pub = time.monotonic()

    def _step(self, u) -> None:
        if self._resends >= self.resend_warn_after:
            self.get_logger().info(f"tick {self.stamp_ns()} ns answered after {self._resends} re-sends")
        self._resends = 0
        res = self.world.step(np.asarray(u, dtype=float))
        self._delta_hold = float(u[1])
        self.clock.advance()
        self._publish_state()
        if res.done:
            self.active = False
            sc = self.world.scenario
            out = I.EpisodeResult(res.outcome, None, sc.n_sv, sc.task, sc.seed, res.steps, self.stamp_ns())
            self.results.append(out)
            self.episodes += 1
            st = I.result_to_status(out)
            w = self.world
            extra = {"n_pcp": int(w.n_pcp), "dist_to_goal": float(w.dist_to_goal()),
                     "speed": float(w.ego[2]), "lane_changes": int(getattr(w, "ev_lane_change_count", 0)),
                     "collided_with": str(res.collided_with or ""), "sim_time": float(w.time)}
            st.values += [I.KeyValue(key=k, value=repr(v) if isinstance(v, float) else str(v))
                          for k, v in extra.items()]
            self.pub_result.publish(st)
            self.get_logger().info(f"episode {self.episodes}: {res.outcome} after {res.steps} steps "
                                   f"(n_sv={sc.n_sv}, task={sc.task}, seed={sc.seed}"
                                   + (f", n_slow={sc.n_slow})" if sc.n_slow else ")"))

    # ------------------------------------------------------------------ commands
    def _on_command(self, msg) -> None:
        u, _ = I.trajectory_to_command(msg)
        stamp = I.stamp_to_ns(msg.header.stamp)
        if self.mode == "realtime":
            if stamp > self.stamp_ns():
                # a command can only answer a state that exists: one stamped after the current
                # tick would otherwise never go stale and be applied until the episode ends
                raise I.MessageError(f"stamped {(stamp - self.stamp_ns()) / I.NS_PER_S:.3f} s after the "
                                     f"current tick (no state to answer yet)")
            self._last_cmd = (stamp, u)
            return
        if self.active and stamp == self.stamp_ns():
            self._step(u)

    def _resend(self) -> None:
        if self.active and time.monotonic() - self._last_pub >= self.resend_period:
            self._publish_state()
            self._resends += 1
            if self._resends == self.resend_warn_after:
                self.get_logger().warning(
                    f"tick {self.stamp_ns()} ns re-sent {self._resends} times without a command for it "
                    "(no controller, or planner and controller refuse this tick: see their logs)")

    def _resend_goal(self) -> None:
        if self.active and self._goal_msg is not None and \
                time.monotonic() - self._last_goal_pub >= self.goal_resend_period:
            self.pub_goal.publish(self._goal_msg)
            self._last_goal_pub = time.monotonic()

    def _realtime_step(self) -> None:
        if not self.active:
            return
        cmd = self._last_cmd
        age = None if cmd is None else self.stamp_ns() - cmd[0]
        if age is None or not 0 <= age <= self.command_timeout_ns:
            u = np.array([self.brake, self._delta_hold])
            if cmd is not None:
                self.get_logger().warning(f"no command within command_timeout_s (newest is {age / I.NS_PER_S:.2f} s "
                                          "old): braking", throttle_duration_sec=5.0)
        else:
            u = cmd[1]
        self._step(u)


def main(argv=None) -> int:
    def make(args):
        if args:
            raise ValueError(f"world_node takes no positional arguments (got {args}); use --ros-args -p ...")
        return WorldNode()
    return run_single(make, argv)


if __name__ == "__main__":
    raise SystemExit(main())
