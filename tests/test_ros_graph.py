"""The ROS graph end to end over real DDS: separate processes, the one-process demo, the MCAP player.

The planner is a stand-in (``StandInPlanner`` below: fixed action, straight-line route,
the package's real action decoding), so these tests need no trained policy; the world,
controller, curriculum, recorder and player are the real nodes.
"""
import os
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from bimacppo_sim import Scenario, World, load_map  # noqa: E402
from bimacppo_sim.ros import interfaces as I  # noqa: E402
from bimacppo_sim.ros import mcap_io  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
STANDIN = "test_ros_graph:StandInPlanner"
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(HERE), os.environ.get("PYTHONPATH", "")]),
           AMENT_PREFIX_PATH=os.environ.get("AMENT_PREFIX_PATH", sys.prefix))
SCENARIO = Scenario(n_sv=1, task="straight", seed=3)
EPISODE_TIMEOUT = 45.0


class StandInPlanner:
    """HighLevelPlanner's API with a fixed action: enough to close the loop deterministically."""

    ACTION = (2, 3, 1)  # third waypoint ahead, 6 m/s, keep lane
    SPACING = 3.0

    @classmethod
    def load(cls, policy_path, map_id):
        return cls(map_id)

    def __init__(self, map_id):
        from bimacppo_planner.decision import EnvConfig
        self.road = load_map(map_id)
        self.cfg = EnvConfig.load()
        self.tracker = None

    def reset(self, ego, goal):
        from bimacppo_planner.decision import WaypointTracker
        start, end = np.asarray(ego[:2], float), np.asarray(goal[:2], float)
        n = max(2, int(np.linalg.norm(end - start) // self.SPACING) + 2)
        pts = start + np.linspace(0.0, 1.0, n)[:, None] * (end - start)
        psi = np.arctan2(*(end - start)[::-1])
        route = np.column_stack([pts, np.full(n, psi)])
        route = np.vstack([route, route[-1] + np.array([np.cos(psi), np.sin(psi), 0.0]) * self.SPACING])
        self.tracker = WaypointTracker(route, self.cfg.action.n_waypoints)
        self.tracker.update(ego[0], ego[1])

    def step(self, ego, svs):
        from bimacppo_planner.decision import decode_action
        self.tracker.update(ego[0], ego[1])
        x_imr, changed = decode_action(self.ACTION, self.tracker, self.cfg.action, self.road.lateral_point)
        return np.asarray(x_imr, float), {"lane_change": changed}


def _as_received(ego, ids, svs, goal):
    """What a node decodes from the standard messages: the yaw quaternion round-trip rounds
    psi by ~1e-16, and the MPC core is sensitive to that (measured: 96 vs 99 steps to the
    same outcome on SCENARIO), so the reference loop sees exactly what the nodes see."""
    e = I.odometry_to_state(I.state_to_odometry(ego, 1))
    _, s = I.objects_to_svs(I.svs_to_objects(ids, svs, 1))
    g = I.pose_to_goal(I.goal_to_pose(goal, 1))
    return e, s, g


def in_process_episode(scenario, map_id="dual_lane_4way"):
    """The same loop without ROS (as IntersectionEnv.step with decision_every = 1)."""
    from bimacppo_mpc import MPCConfig, make_controller
    world = World(load_map(map_id))
    world.reset(scenario)
    hp = StandInPlanner(map_id)
    ego, _, goal = _as_received(world.ego, world.sv_ids, world.sv_states(), world.goal)
    hp.reset(ego, goal)
    ctrl = make_controller(MPCConfig.load(), solver="fast")
    ctrl.reset()
    u_prev = np.zeros(2)
    traj = [world.ego]
    while True:
        ego, svs, _ = _as_received(world.ego, world.sv_ids, world.sv_states(), world.goal)
        x_imr, _ = hp.step(ego, svs)
        sol = ctrl.solve(ego, x_imr, u_prev)
        res = world.step(sol.u)
        u_prev = np.asarray(sol.u, float)
        traj.append(world.ego)
        if res.done:
            return res.outcome, np.array(traj)


def _start(*args):
    return subprocess.Popen([sys.executable, *args], env=ENV, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _stop_all(procs):
    outs = []
    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            out, _ = p.communicate(timeout=15)
        except subprocess.TimeoutExpired:
            p.kill()
            out, _ = p.communicate()
        outs.append(out)
    return outs


@pytest.fixture(scope="module")
def node():
    rclpy.init()
    n = rclpy.create_node("test_ros_graph")
    yield n
    n.destroy_node()
    rclpy.try_shutdown()


def _wait_ready(node, timeout=30.0):
    """Planner and controller are up once their state subscriptions exist (map loading takes s)."""
    def ready():
        names = {i.node_name for i in node.get_subscriptions_info_by_topic(I.TOPIC_EGO_ODOM)}
        return {"planner", "controller"} <= names
    assert _collect(node, ready, timeout), "planner/controller did not come up"


def _collect(node, until, timeout):
    t_end = time.monotonic() + timeout
    while not until() and time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.05)
    return until()


def test_lockstep_processes_match_in_process_run(node):
    ref_outcome, ref_traj = in_process_episode(SCENARIO)
    odoms, results = {}, []
    s1 = node.create_subscription(I.Odometry, I.TOPIC_EGO_ODOM,
                                  lambda m: odoms.setdefault(I.stamp_to_ns(m.header.stamp), I.odometry_to_state(m)),
                                  I.STATE_QOS)
    s2 = node.create_subscription(I.DiagnosticStatus, I.TOPIC_RESULT,
                                  lambda m: results.append(I.status_to_result(m)), I.RESULT_QOS)
    procs = [
        _start("-m", "bimacppo_planner.ros.planner_node", "--ros-args", "-p", f"planner_class:={STANDIN}"),
        _start("-m", "bimacppo_mpc.ros.controller_node"),
    ]
    time.sleep(1.0)  # let the others come up; the world's resend covers any late joiner anyway
    procs.append(_start("-m", "bimacppo_sim.ros.world_node", "--ros-args", "-p", "mode:=lockstep",
                        "-p", f"scenario.n_sv:={SCENARIO.n_sv}", "-p", f"scenario.task:={SCENARIO.task}",
                        "-p", f"scenario.seed:={SCENARIO.seed}"))
    try:
        ok = _collect(node, lambda: bool(results), EPISODE_TIMEOUT)
    finally:
        outs = _stop_all(procs)
        node.destroy_subscription(s1)
        node.destroy_subscription(s2)
    assert ok, "no episode result; process output:\n" + "\n---\n".join(outs)
    assert all(p.returncode == 0 for p in procs), outs
    res = results[0]
    assert res.outcome == ref_outcome
    assert res.steps == len(ref_traj) - 1
    stamps = sorted(odoms)
    traj = np.array([odoms[s] for s in stamps if s <= res.stamp_ns])[-len(ref_traj):]
    assert traj.shape == ref_traj.shape
    assert np.allclose(traj[:, :3], ref_traj[:, :3], atol=1e-6)
    assert np.allclose(np.cos(traj[:, 3] - ref_traj[:, 3]), 1.0, atol=1e-9)


@pytest.fixture(scope="module")
def demo_mcap(tmp_path_factory):
    """Two episodes of the one-process demo, recorded (shared by the tests below)."""
    mcap = tmp_path_factory.mktemp("demo") / "demo.mcap"
    demo = _start("-m", "bimacppo_planner.ros.graph", "--episodes", "2", "--scheduler", "random",
                  "--planner-class", STANDIN, "--output", str(mcap), "--timeout", "60")
    out, _ = demo.communicate(timeout=90)
    return mcap, demo.returncode, out


def test_graph_demo_records_every_topic(demo_mcap):
    mcap, rc, out = demo_mcap
    assert rc == 0, out
    assert "episodes: 2" in out and f"mcap: {mcap}" in out
    report = mcap_io.ReadReport()
    for _ in mcap_io.iter_mcap(mcap, report):
        pass
    assert report.complete, report.error
    for topic in (I.TOPIC_CLOCK, I.TOPIC_EGO_ODOM, I.TOPIC_OBJECTS, I.TOPIC_MARKERS, I.TOPIC_GOAL,
                  I.TOPIC_REFERENCE, I.TOPIC_COMMAND, I.TOPIC_RESULT, I.TOPIC_PLANNER_RESULT,
                  I.TOPIC_PLANNER_MARKERS):
        assert report.topics.get(topic, 0) > 0, (topic, report.topics)
    assert report.topics[I.TOPIC_RESULT] == 2


@pytest.mark.slow
@pytest.mark.xfail(reason="known issue: with the player as source, the controller answers only a few "
                          "of the replayed ticks (see docs/ros.md, open issues)", strict=False)
def test_player_drives_planner_and_controller(node, demo_mcap):
    mcap, rc, out = demo_mcap
    assert rc == 0, out
    report = mcap_io.ReadReport()
    recorded_cmds = {}
    from mcap_ros2.decoder import DecoderFactory
    dec = DecoderFactory()
    for sch, ch, m in mcap_io.iter_mcap(mcap, report):
        if ch.topic == I.TOPIC_COMMAND:
            msg = dec.decoder_for("cdr", sch)(m.data)
            if msg.header.stamp.sec < 10**6:  # tick-stamped answers, not wall-stamped watchdog stops
                recorded_cmds[(msg.header.stamp.sec, msg.header.stamp.nanosec)] = msg.points[0].accelerations[1]
    # the recording stands in for the world: planner + controller answer its states
    cmds = {}
    sub = node.create_subscription(
        I.JointTrajectory, I.TOPIC_COMMAND,
        lambda m: cmds.setdefault((m.header.stamp.sec, m.header.stamp.nanosec), m.points[0].accelerations[1]),
        I.STATE_QOS)
    procs = [
        _start("-m", "bimacppo_planner.ros.planner_node", "--ros-args", "-p", f"planner_class:={STANDIN}"),
        _start("-m", "bimacppo_mpc.ros.controller_node"),
    ]
    _wait_ready(node)
    world_topics = "[" + ",".join(f"'{t}'" for t in (I.TOPIC_CLOCK, I.TOPIC_EGO_ODOM, I.TOPIC_OBJECTS,
                                                     I.TOPIC_GOAL, I.TOPIC_RESULT)) + "]"
    player = _start("-m", "bimacppo_sim.ros.player", str(mcap), "--ros-args", "-p", "rate:=1.0",
                    "-p", f"topics:={world_topics}", "-p", "start_delay_s:=1.5")
    try:
        _collect(node, lambda: player.poll() is not None, 60)
        _collect(node, lambda: False, 1.0)
    finally:
        outs = _stop_all(procs + [player])
        node.destroy_subscription(sub)
    assert player.returncode == 0, outs[-1]
    common = set(cmds) & set(recorded_cmds)
    # every state the world published in the recording got a command again ...
    assert len(common) >= 0.9 * len(recorded_cmds), (len(common), len(recorded_cmds), outs)
    # ... and the same one: same inputs, same deterministic planner and MPC
    assert all(abs(cmds[k] - recorded_cmds[k]) < 1e-6 for k in common)
