"""Another simulator in place of the world, written from docs/interfaces.md ("Bringing
another simulator"): its junction lies far from the origin of ``map`` and is rotated.

``ForeignSim`` is a small rclpy node of this test; it uses nothing of ``bimacppo_sim``'s
world (its own bicycle integration, its own episode bookkeeping, its own SV). It knows
where its junction is, and the planner gets the matching map file (the shipped
dual-lane junction with a ``pose``). It runs two episodes in lockstep with the real
planner and controller nodes: a straight crossing with one SV crossing from the west,
then a right turn with no SVs, sent as an /objects message with no point at all. It
sends no ``n_pcp``: the planner infers it from its map.
"""
import math
import time

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from rclpy.clock import Clock, ClockType  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rosgraph_msgs.msg import Clock as ClockMsg  # noqa: E402

from bimacppo_interfaces import contract as I  # noqa: E402

# --- the foreign simulator's own description of its junction (docs/interfaces.md numbers)
POSE = (412.0, -318.5, 0.6)       # junction centre (m) and rotation (rad) in the map frame
LANE_W = 3.5                      # m; two lanes per direction, kerb radius 8 m: box half-size 15 m
DT = 0.1                          # s, one tick
WHEELBASE = 2.875
A_MIN, A_MAX, DELTA_MAX, V_MAX = -6.0, 3.0, 0.6, 12.0
GOAL_LINE_HALF = 2 * LANE_W       # success: the EV crosses the goal line (across its heading) within this
MAX_TICKS = 300                   # 30 s: timeout
RESEND_S = 0.5
TIMEOUT_S = 120.0
# episodes in the junction's own coordinates: EV start (x, y, v, psi), goal (x, y, psi), SVs
EPISODES = [
    dict(task="straight", start=(0.5 * LANE_W, -50.0, 5.0, math.pi / 2),
         goal=(0.5 * LANE_W, 40.0, math.pi / 2),
         svs={"west_car": (-40.0, -0.5 * LANE_W, 10.0, 0.0)}),     # crossing west -> east, inner lane
    dict(task="right", start=(1.5 * LANE_W, -50.0, 5.0, math.pi / 2),
         goal=(40.0, -1.5 * LANE_W, 0.0), svs={}),
]


def to_map(x, y, psi):
    """Junction coordinates -> the map frame (what goes on the wire)."""
    c, s = math.cos(POSE[2]), math.sin(POSE[2])
    return POSE[0] + c * x - s * y, POSE[1] + s * x + c * y, math.atan2(math.sin(psi + POSE[2]),
                                                                       math.cos(psi + POSE[2]))


class ForeignSim(Node):
    """Lockstep source per docs/interfaces.md; integrates in the map frame."""

    def __init__(self, episodes):
        super().__init__("foreign_sim")
        self.episodes = list(episodes)
        self.tick = 0
        self.active = False
        self.outcomes, self.commands, self.ticks = [], [], []
        self.far = []                 # the EV's distance from the map origin, every tick
        self.pub_clock = self.create_publisher(ClockMsg, I.TOPIC_CLOCK, I.CLOCK_QOS)
        self.pub_odom = self.create_publisher(I.Odometry, I.TOPIC_EGO_ODOM, I.STATE_QOS)
        self.pub_objects = self.create_publisher(I.MultiDOFJointTrajectory, I.TOPIC_OBJECTS, I.STATE_QOS)
        self.pub_goal = self.create_publisher(I.PoseStamped, I.TOPIC_GOAL, I.LATCHED_QOS)
        self.pub_result = self.create_publisher(I.DiagnosticStatus, I.TOPIC_RESULT, I.RESULT_QOS)
        self.create_subscription(I.JointTrajectory, I.TOPIC_COMMAND, self._on_command, I.STATE_QOS)
        self._last_pub = 0.0
        self.create_timer(0.05, self._resend, clock=Clock(clock_type=ClockType.STEADY_TIME))

    @property
    def done(self):
        return not self.active and not self.episodes

    def stamp(self):
        return self.tick * round(DT * I.NS_PER_S)

    def start_next(self):
        ep = self.episodes.pop(0)
        x, y, psi = to_map(ep["start"][0], ep["start"][1], ep["start"][3])
        self.ev = [x, y, ep["start"][2], psi]
        self.goal = to_map(*ep["goal"])
        self.svs = {k: [*to_map(s[0], s[1], s[3])[:2], s[2], to_map(s[0], s[1], s[3])[2]]
                    for k, s in ep["svs"].items()}
        self.task, self.steps = ep["task"], 0
        self.tick += 1                                   # stamps only grow, also across episodes
        self.active = True
        self.pub_goal.publish(I.goal_to_pose(self.goal, self.stamp()))   # stamped with the first tick
        self._publish()

    def _publish(self):
        s = self.stamp()
        self.pub_clock.publish(ClockMsg(clock=I.ns_to_stamp(s)))
        self.pub_odom.publish(I.state_to_odometry(self.ev, s))
        if self.svs:
            self.pub_objects.publish(I.svs_to_objects(list(self.svs), list(self.svs.values()), s))
        else:                                            # no SVs: no joint names and no point at all
            msg = I.MultiDOFJointTrajectory()
            msg.header.stamp, msg.header.frame_id = I.ns_to_stamp(s), I.FRAME_MAP
            self.pub_objects.publish(msg)
        if self.active and (not self.ticks or self.ticks[-1] != s):
            self.ticks.append(s)
            self.far.append(math.hypot(self.ev[0], self.ev[1]))
        self._last_pub = time.monotonic()

    def _resend(self):
        if self.active and time.monotonic() - self._last_pub > RESEND_S:
            self._publish()

    def _on_command(self, msg):
        u, _ = I.trajectory_to_command(msg)
        stamp = I.stamp_to_ns(msg.header.stamp)
        self.commands.append(stamp)
        if not (self.active and stamp == self.stamp()):
            return                                       # a repeat, or not an answer to this tick
        a = min(max(float(u[0]), A_MIN), A_MAX)
        d = min(max(float(u[1]), -DELTA_MAX), DELTA_MAX)
        x, y, v, psi = self.ev
        self.ev = [x + v * math.cos(psi + d) * DT, y + v * math.sin(psi + d) * DT,
                   min(max(v + a * DT, 0.0), V_MAX), psi + 2.0 * v / WHEELBASE * math.sin(d) * DT]
        self.ev[3] = math.atan2(math.sin(self.ev[3]), math.cos(self.ev[3]))
        for sv in self.svs.values():                     # SVs keep their lane and speed
            sv[0] += sv[2] * math.cos(sv[3]) * DT
            sv[1] += sv[2] * math.sin(sv[3]) * DT
        self.tick += 1
        self.steps += 1
        dx, dy, gc, gs = self.ev[0] - self.goal[0], self.ev[1] - self.goal[1], math.cos(self.goal[2]), \
            math.sin(self.goal[2])
        crossed = dx * gc + dy * gs >= 0.0 and abs(-dx * gs + dy * gc) <= GOAL_LINE_HALF
        dist = math.hypot(dx, dy)
        outcome = "success" if crossed else "timeout" if self.steps >= MAX_TICKS else None
        self.active = outcome is None
        self._publish()                                  # the next state, or the terminal one
        if outcome is None:
            return
        st = I.result_to_status(I.EpisodeResult(outcome, None, len(self.svs), self.task, 0, self.steps,
                                                self.stamp()))
        st.values += [I.KeyValue(key="dist_to_goal", value=repr(dist)),
                      I.KeyValue(key="speed", value=repr(self.ev[2]))]
        self.pub_result.publish(st)
        self.outcomes.append((outcome, self.steps, dist))
        if self.episodes:
            self.start_next()


@pytest.fixture(scope="module")
def map_file(tmp_path_factory):
    from bimacppo_sim.road import MAP_DIR
    spec = yaml.safe_load((MAP_DIR / "dual_lane_4way.yaml").read_text())
    spec.update(id="foreign_junction", pose={"x": POSE[0], "y": POSE[1], "heading": POSE[2]})
    path = tmp_path_factory.mktemp("map") / "foreign_junction.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def test_planner_and_controller_drive_a_foreign_source_whose_junction_is_elsewhere(map_file):
    from bimacppo_mpc.ros.controller_node import ControllerNode
    from bimacppo_planner.ros.planner_node import PlannerNode
    from bimacppo_sim import load_map

    rclpy.init()
    nodes, ex = [], SingleThreadedExecutor()
    try:
        sim_time = Parameter("use_sim_time", value=True)
        planner = PlannerNode(parameter_overrides=[Parameter("map_id", value=str(map_file)), sim_time])
        ctrl = ControllerNode(parameter_overrides=[sim_time])
        sim = ForeignSim(EPISODES)
        probe = Node("probe")
        results = []
        probe.create_subscription(I.DiagnosticStatus, I.TOPIC_PLANNER_RESULT, results.append, I.RESULT_QOS)
        nodes = [planner, ctrl, sim, probe]
        for n in nodes:
            ex.add_node(n)
        sim.start_next()
        t_end = time.monotonic() + TIMEOUT_S
        while not (sim.done and len(results) == len(EPISODES)) and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
        dropped = dict(planner.dropped), dict(ctrl.dropped)
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()
    assert sim.done, f"loop stalled at tick {sim.tick}; outcomes {sim.outcomes}; dropped {dropped}"
    assert min(sim.far) > 300.0                        # the whole run far from the map origin
    assert set(sim.ticks) <= set(sim.commands), sorted(set(sim.ticks) - set(sim.commands))[:5]
    # the planner drives it through a junction it only knows from the map file's pose
    assert [o for o, _, _ in sim.outcomes] == ["success", "success"], sim.outcomes
    assert [I.status_to_result(r).outcome for r in results] == ["success", "success"]
    facts = [I.result_extras(r) for r in results]
    assert all(math.isfinite(float(f["return"])) for f in facts)
    road = load_map(map_file)
    crossing = road.connector_conflicts(road.ev_connector(0, "straight"), "west_in_0>east_out_0")
    assert crossing >= 1 and [int(f["n_pcp"]) for f in facts] == [crossing, 0]
    assert not dropped[0].get(I.TOPIC_OBJECTS), dropped   # the point-less /objects was accepted
    assert np.isfinite(sim.far).all()
