"""The ROS graph end to end over real DDS: separate processes, the one-process demo, the MCAP player.

Every node is the real one, the planner included: ``HighLevelPlanner`` with a small
untrained policy exported by the test (``policy_file``), so no shipped policy is needed.
An untrained policy still acts deterministically (argmax), which is all these tests need.
"""
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from bimacppo_sim import Scenario, World, load_map  # noqa: E402
from bimacppo_interfaces import contract as I  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from bimacppo_bag import mcap_io  # noqa: E402

ENV = dict(os.environ, AMENT_PREFIX_PATH=os.environ.get("AMENT_PREFIX_PATH", sys.prefix))
SCENARIO = Scenario(n_sv=2, task="straight", seed=1)
POLICY_SEED = 1   # an untrained policy that changes lanes on SCENARIO (so the return has both terms)
EPISODE_TIMEOUT = 45.0
DISCOVERY_TIMEOUT = 30.0   # a new process imports torch / numba before its node exists
WORLD_TOPICS = (I.TOPIC_CLOCK, I.TOPIC_EGO_ODOM, I.TOPIC_OBJECTS, I.TOPIC_GOAL, I.TOPIC_RESULT)


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory):
    from bimacppo_learning.checkpoint import export_policy
    from bimacppo_learning.ppo import PPO
    path = tmp_path_factory.mktemp("policy") / "policy.pt"
    export_policy(PPO(16, (5, 5, 3), seed=POLICY_SEED), path)
    return path


@pytest.fixture(scope="module")
def policy_file_extended(tmp_path_factory):
    """A policy whose metadata carries the shipped configuration (ego-frame observation,
    one decision every 3 ticks): the planner node must observe and hold decisions as training did."""
    from importlib import resources

    from bimacppo_learning.checkpoint import export_policy
    from bimacppo_planner.decision import EnvConfig
    from bimacppo_learning.ppo import PPO
    cfg = EnvConfig.load(resources.files("bimacppo_learning").joinpath("config/env_extended.yaml"))
    assert cfg.action.decision_every == 3 and cfg.observation.sv_frame == "ego"
    path = tmp_path_factory.mktemp("policy_ext") / "policy.pt"
    export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=POLICY_SEED), path, meta={"env_config": cfg.to_dict()})
    return path


def _as_received(ego, ids, svs, goal):
    """What a node decodes from the standard messages: the yaw quaternion round-trip rounds
    psi by ~1e-16, and the MPC core is sensitive to that (measured with a fixed-action
    planner: 96 vs 99 steps to the same outcome on Scenario(1, "straight", 3)), so the reference loop sees
    exactly what the nodes see."""
    e = I.odometry_to_state(I.state_to_odometry(ego, 1))
    _, s = I.objects_to_svs(I.svs_to_objects(ids, svs, 1))
    g = I.pose_to_goal(I.goal_to_pose(goal, 1))
    return e, s, g


def in_process_episode(scenario, policy_path, map_id="dual_lane_4way"):
    """The same loop without ROS, as ``IntersectionEnv.reset/step`` with the deployed
    ``HighLevelPlanner`` choosing the actions (one decision every ``decision_every`` ticks,
    held in between); the return is summed with the environment's ``step_reward``, one term per
    decision plus the terminal term. Returns (outcome, trajectory, return, lane changes)."""
    from bimacppo_mpc import MPCConfig, make_controller
    from bimacppo_planner.agent import HighLevelPlanner
    from bimacppo_planner.decision import step_reward
    world = World(load_map(map_id))
    world.reset(scenario)
    hp = HighLevelPlanner.load(policy_path, map_id)
    every = hp.cfg.action.decision_every
    ego, _, goal = _as_received(world.ego, world.sv_ids, world.sv_states(), world.goal)
    hp.reset(ego, goal)
    ctrl = make_controller(MPCConfig.load(), solver="fast")
    ctrl.reset()
    u_prev = np.zeros(2)
    traj, ret, changes, tick = [world.ego], 0.0, 0, 0
    while True:
        ego, svs, _ = _as_received(world.ego, world.sv_ids, world.sv_states(), world.goal)
        if tick % every == 0:
            x_imr, info = hp.step(ego, svs)
            changes += int(info["lane_change"])
            ret += step_reward(hp.cfg.reward, info["lane_change"])
        sol = ctrl.solve(ego, x_imr, u_prev)
        res = world.step(sol.u)
        u_prev = np.asarray(sol.u, float)
        traj.append(world.ego)
        tick += 1
        if res.done:
            ret += step_reward(hp.cfg.reward, False, res.outcome, scenario.n_sv, int(world.n_pcp),
                               float(world.ego[2]), float(world.dist_to_goal())) - hp.cfg.reward.step
            return res.outcome, np.array(traj), ret, changes


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


def _collect(node, until, timeout):
    t_end = time.monotonic() + timeout
    while not until() and time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.05)
    return until()


def _await_publisher(node, sub, timeout=DISCOVERY_TIMEOUT):
    """Wait until ``sub`` is matched with a publisher (discovery of a new process)."""
    assert _collect(node, lambda: sub.get_publisher_count() > 0, timeout), \
        f"no publisher on {sub.topic_name} after {timeout} s"


def _planner(policy_file, *extra):
    return _start("-m", "bimacppo_planner.ros.planner_node", "--ros-args",
                  "-p", f"policy_path:={policy_file}", *extra)


# The observer compares every tick of the episode, so it keeps them all: with the contract's
# depth of 10 (enough for the nodes, which use the newest state) a reader whose spin lags the
# lockstep loop on a loaded machine has older ticks overwritten in its queue before it takes them.
OBSERVER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5000, reliability=ReliabilityPolicy.RELIABLE,
                          durability=DurabilityPolicy.VOLATILE)


@pytest.fixture(scope="module")
def policy_file_overtaking(tmp_path_factory):
    """A policy with the shipped overtaking policy's configuration (the three-lane road's lead
    features, lane changes from the chosen lane): the planner node must observe and decode as
    its env did, on a world whose slow SVs are drawn from the seed."""
    from bimacppo_learning.checkpoint import export_policy
    from bimacppo_learning.ppo import PPO
    from bimacppo_planner.decision import EnvConfig
    from conftest import REPO
    cfg = EnvConfig.load(REPO / "studies/config/env_wait_chord_junction_road_overtake_chosen_queue_leads.yaml")
    assert cfg.observation.leads and cfg.action.lane_change_from == "chosen"
    path = tmp_path_factory.mktemp("policy_ot") / "policy.pt"
    export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=POLICY_SEED), path,
                  meta={"env_config": cfg.to_dict(), "map": "three_lane_straight"})
    return path


def _overtaking_scenario():
    """The first validation scenario of the overtaking protocol (3 SVs, at most 2 slow) in which
    two SVs drive slowly."""
    from bimacppo_learning.seed_sets import eval_seed
    from bimacppo_sim import draw_n_slow
    seed = next(s for s in (eval_seed(1, 3, k, "validation") for k in range(1000)) if draw_n_slow(s, 3, 2) == 2)
    return Scenario(n_sv=3, task="straight", seed=seed, n_slow=2)


@pytest.mark.parametrize("which", ["paper", "extended", "overtaking"])
def test_lockstep_processes_match_in_process_run(node, policy_file, policy_file_extended, policy_file_overtaking,
                                                 which):
    policy_file = {"paper": policy_file, "extended": policy_file_extended, "overtaking": policy_file_overtaking}[which]
    scenario = _overtaking_scenario() if which == "overtaking" else SCENARIO
    map_id = "three_lane_straight" if which == "overtaking" else "dual_lane_4way"
    ref_outcome, ref_traj, ref_return, ref_changes = in_process_episode(scenario, policy_file, map_id)
    if which == "paper":
        assert ref_changes > 0, "POLICY_SEED should give a policy that changes lanes on SCENARIO"
    odoms, objects, results, returns = {}, {}, [], []
    subs = [
        node.create_subscription(I.Odometry, I.TOPIC_EGO_ODOM,
                                 lambda m: odoms.setdefault(I.stamp_to_ns(m.header.stamp), I.odometry_to_state(m)),
                                 OBSERVER_QOS),
        node.create_subscription(I.MultiDOFJointTrajectory, I.TOPIC_OBJECTS,
                                 lambda m: objects.setdefault(I.stamp_to_ns(m.header.stamp), I.objects_to_svs(m)[1]),
                                 OBSERVER_QOS),
        node.create_subscription(I.DiagnosticStatus, I.TOPIC_RESULT,
                                 lambda m: results.append(I.status_to_result(m)), I.RESULT_QOS),
        node.create_subscription(I.DiagnosticStatus, I.TOPIC_PLANNER_RESULT,
                                 lambda m: returns.append(I.status_to_result(m)), I.RESULT_QOS),
    ]
    # Both results are volatile, so this observer is matched with each of their publishers
    # before the episode can end: planner, world, and only then the controller (the world
    # cannot step before the controller answers, so no result exists before the last start).
    procs = [_planner(policy_file, "-p", f"map_id:={map_id}")]
    try:
        _await_publisher(node, subs[3])
        procs.append(_start("-m", "bimacppo_sim.ros.world_node", "--ros-args", "-p", "mode:=lockstep",
                            "-p", f"map_id:={map_id}", "-p", f"scenario.n_sv:={scenario.n_sv}",
                            "-p", f"scenario.task:={scenario.task}", "-p", f"scenario.seed:={scenario.seed}",
                            "-p", f"scenario.slow_svs:={2 if which == 'overtaking' else 0}"))
        _await_publisher(node, subs[2]), _await_publisher(node, subs[1]), _await_publisher(node, subs[0])
        # This side's match does not mean the world's writers have matched this observer (each side
        # discovers the other on its own; on a loaded machine seconds apart), and a volatile writer
        # drops what it sent before. The world re-sends tick 0 until the controller answers, so a
        # received tick-0 state and SV list show both writers reach the observer before it steps.
        assert _collect(node, lambda: bool(odoms) and bool(objects), DISCOVERY_TIMEOUT), \
            f"the world's tick 0 did not reach the observer within {DISCOVERY_TIMEOUT} s"
        procs.append(_start("-m", "bimacppo_mpc.ros.controller_node"))
        ok = _collect(node, lambda: bool(results) and bool(returns), EPISODE_TIMEOUT)
    finally:
        outs = _stop_all(procs)
        for s in subs:
            node.destroy_subscription(s)
    assert ok, (f"no {'episode result' if not results else 'planner return'}; process output:\n"
                + "\n---\n".join(outs))
    assert all(p.returncode == 0 for p in procs), (
        "exit codes planner / world / controller: " + ", ".join(str(p.returncode) for p in procs)
        + "; process output:\n" + "\n---\n".join(outs))
    res = results[0]
    assert res.outcome == ref_outcome
    assert res.steps == len(ref_traj) - 1
    stamps = sorted(odoms)
    traj = np.array([odoms[s] for s in stamps if s <= res.stamp_ns])[-len(ref_traj):]
    assert traj.shape == ref_traj.shape
    assert np.allclose(traj[:, :3], ref_traj[:, :3], atol=1e-6)
    assert np.allclose(np.cos(traj[:, 3] - ref_traj[:, 3]), 1.0, atol=1e-9)
    # the planner's return (step_reward over its own decisions + the world's terminal facts)
    # is the return the environment's reward gives the same episode
    assert returns[0].outcome == res.outcome and returns[0].stamp_ns == res.stamp_ns
    assert returns[0].episode_return == pytest.approx(ref_return, abs=1e-9)
    # the SVs of the episode's first tick are the in-process world's (the slow ones included:
    # an SV starts at a share of its desired speed, which slowing scales)
    first = [t for t in stamps if t <= res.stamp_ns][-len(ref_traj)]
    ref_world = World(load_map(map_id))
    ref_world.reset(scenario)
    svs0 = ref_world.sv_states()
    assert objects[first].shape == svs0.shape and np.allclose(objects[first][:, :3], svs0[:, :3], atol=1e-6)
    if which == "overtaking":
        v_normal = World(load_map(map_id))
        v_normal.reset(Scenario(n_sv=3, task="straight", seed=scenario.seed, n_slow=0))
        slowed = svs0[:, 2] < v_normal.sv_states()[:, 2] - 1e-6
        assert slowed.sum() == 2


@pytest.fixture(scope="module")
def demo_mcap(tmp_path_factory, policy_file):
    """Two episodes of the one-process demo, recorded (shared by the tests below)."""
    mcap = tmp_path_factory.mktemp("demo") / "demo.mcap"
    demo = _start("-m", "bimacppo_bringup.graph", "--episodes", "2", "--scheduler", "random",
                  "--policy", str(policy_file), "--output", str(mcap), "--timeout", "60")
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
    assert report.topics[I.TOPIC_PLANNER_RESULT] == 2  # a return for every episode


def _recorded(mcap):
    """Tick stamps of the recorded states, the episodes' first stamps (goal stamps) and the
    recorded tick-stamped commands (a, delta)."""
    from mcap_ros2.decoder import DecoderFactory
    dec = DecoderFactory()
    ticks, goals, cmds = [], [], {}
    for sch, ch, m in mcap_io.iter_mcap(mcap, topics=[I.TOPIC_EGO_ODOM, I.TOPIC_COMMAND, I.TOPIC_RESULT,
                                                      I.TOPIC_GOAL]):
        msg = dec.decoder_for("cdr", sch)(m.data)
        if ch.topic == I.TOPIC_EGO_ODOM:
            ticks.append(I.stamp_to_ns(msg.header.stamp))
        elif ch.topic == I.TOPIC_GOAL:
            goals.append(I.stamp_to_ns(msg.header.stamp))
        elif ch.topic == I.TOPIC_RESULT:
            ticks.remove(int({kv.key: kv.value for kv in msg.values}["stamp_ns"]))  # terminal: no answer
        else:
            cmds[I.stamp_to_ns(msg.header.stamp)] = (msg.points[0].accelerations[1], msg.points[0].positions[0])
    return sorted(set(ticks)), sorted(set(goals)), cmds


def _until_first_gap(ticks, goals, answered):
    """The ticks of each episode before its first unanswered one: there the live planner and
    MPC have seen exactly the recorded history (tracker, warm start), so must match it."""
    out, gap = [], False
    for t in ticks:
        if t in goals:
            gap = False
        gap = gap or t not in answered
        if not gap:
            out.append(t)
    return out


@pytest.mark.parametrize("rate", [pytest.param(1.0, marks=pytest.mark.slow), 4.0])
def test_player_drives_planner_and_controller(node, demo_mcap, policy_file, rate):
    """The recording stands in for the world: replayed in realtime style (paced by its /clock;
    rate 1.0 = 10 ticks/s, the default run uses 4.0 = 40 ticks/s to stay short), live planner
    + controller answer its states. Open loop: the player does not wait for answers, so an
    answer may be missed under load; at least 90 % must come, and they must be the recorded
    commands (same inputs, deterministic planner and MPC) up to an episode's first miss."""
    mcap, rc, out = demo_mcap
    assert rc == 0, out
    ticks, goals, recorded_cmds = _recorded(mcap)
    assert len(ticks) > 50 and len(goals) == 2 and set(ticks) <= set(recorded_cmds)
    cmds, other = {}, []

    def on_cmd(m):
        stamp = I.stamp_to_ns(m.header.stamp)
        if stamp in recorded_cmds:
            cmds.setdefault(stamp, (m.points[0].accelerations[1], m.points[0].positions[0]))
        else:
            other.append(stamp)
    sub = node.create_subscription(I.JointTrajectory, I.TOPIC_COMMAND, on_cmd, I.STATE_QOS)
    sim_time = ("-p", "use_sim_time:=true")
    procs = [_planner(policy_file, *sim_time),
             _start("-m", "bimacppo_mpc.ros.controller_node", "--ros-args", *sim_time)]
    try:   # this observer hears the controller, and planner and controller see each other's
        # reference endpoints, before any tick exists: a replay is open loop, so a tick whose
        # reference is lost to discovery is never answered
        _await_publisher(node, sub)
        assert _collect(node, lambda: node.count_publishers(I.TOPIC_REFERENCE) > 0
                        and node.count_subscribers(I.TOPIC_REFERENCE) > 0, DISCOVERY_TIMEOUT), \
            f"planner and controller not both on {I.TOPIC_REFERENCE} after {DISCOVERY_TIMEOUT} s"
    except AssertionError:
        _stop_all(procs)
        raise
    # the player starts once planner and controller are matched on /ego/odom and /objects
    player = _start("-m", "bimacppo_bag.player", str(mcap), "--ros-args", "-p", f"rate:={rate}",
                    "-p", "timing:=clock", "-p", "as_world:=true", "-p", "wait_subscribers:=2",
                    "-p", "start_delay_s:=1.5")
    try:
        _collect(node, lambda: player.poll() is not None, 120)
        _collect(node, lambda: False, 0.5)
    finally:
        outs = _stop_all(procs + [player])
        node.destroy_subscription(sub)
    assert player.returncode == 0, outs[-1]
    answered = [t for t in ticks if t in cmds]
    assert len(answered) >= 0.9 * len(ticks), (len(answered), len(ticks), outs)
    same = _until_first_gap(ticks, goals, set(answered))
    assert len(same) >= 0.5 * len(ticks), (len(same), len(ticks))
    assert all(np.allclose(cmds[t], recorded_cmds[t], atol=1e-6) for t in same)
    # with use_sim_time the watchdog follows the replayed /clock: no safe stop was injected
    assert not other, other[:5]
