"""The world node replaced by a plain publisher: planner + controller only need the topics.

``ScriptedWorld`` is a tiny rclpy node written here, not the package's world node: it steps
a ``World`` itself and publishes /clock, /ego/odom, /objects, /goal_pose and
/episode/result in lockstep (next tick only once the command stamped with the current
tick arrives; re-send after 0.5 s, as docs/interfaces.md asks of any source). The real
planner (``HighLevelPlanner`` with a test-made policy) and controller nodes run with
``use_sim_time`` on its /clock, over real DDS, in one executor.
"""
import math
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from rclpy.clock import Clock, ClockType  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rosgraph_msgs.msg import Clock as ClockMsg  # noqa: E402

from bimacppo_sim import Scenario, World, load_map  # noqa: E402
from bimacppo_interfaces import contract as I  # noqa: E402

MAP = "dual_lane_4way"
POLICY_SEED = 0
EPISODES = (Scenario(n_sv=2, task="straight", seed=1), Scenario(n_sv=1, task="straight", seed=3))
RESEND_S = 0.5
TIMEOUT_S = 60.0


class ScriptedWorld(Node):
    """Lockstep source of the world's topics; records every command it receives."""

    def __init__(self, scenarios):
        super().__init__("scripted_world")
        self.world = World(load_map(MAP))
        self.dt_ns = int(round(self.world.dt * I.NS_PER_S))
        self.scenarios = list(scenarios)
        self.tick = 0
        self.active = False
        self.ticks = []          # stamps of the states that need an answer (not terminal ones)
        self.commands = []       # (stamp, u, horizon) of every command received
        self.outcomes = []
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
        return not self.active and not self.scenarios

    def stamp(self):
        return self.tick * self.dt_ns

    def start_next(self):
        self.world.reset(self.scenarios.pop(0))
        self.tick += 1
        self.active = True
        self.pub_goal.publish(I.goal_to_pose(self.world.goal, self.stamp()))
        self._publish()

    def _publish(self):
        s, w = self.stamp(), self.world
        self.pub_clock.publish(ClockMsg(clock=I.ns_to_stamp(s)))
        self.pub_odom.publish(I.state_to_odometry(w.ego, s))
        self.pub_objects.publish(I.svs_to_objects(w.sv_ids, w.sv_states(), s))
        if self.active and (not self.ticks or self.ticks[-1] != s):
            self.ticks.append(s)
        self._last_pub = time.monotonic()

    def _resend(self):
        if self.active and time.monotonic() - self._last_pub > RESEND_S:
            self._publish()

    def _on_command(self, msg):
        u, horizon = I.trajectory_to_command(msg)
        stamp = I.stamp_to_ns(msg.header.stamp)
        self.commands.append((stamp, u, horizon))
        if not (self.active and stamp == self.stamp()):
            return  # a repeat of an answered tick, or not an answer to a tick at all
        res = self.world.step(u)
        self.tick += 1
        if not res.done:
            self._publish()
            return
        self.active = False
        sc, w = self.world.scenario, self.world
        st = I.result_to_status(I.EpisodeResult(res.outcome, None, sc.n_sv, sc.task, sc.seed, res.steps,
                                                self.stamp()))
        st.values += [I.KeyValue(key="n_pcp", value=str(int(w.n_pcp))),
                      I.KeyValue(key="dist_to_goal", value=repr(float(w.dist_to_goal()))),
                      I.KeyValue(key="speed", value=repr(float(w.ego[2])))]
        self.pub_clock.publish(ClockMsg(clock=I.ns_to_stamp(self.stamp())))
        self.pub_odom.publish(I.state_to_odometry(w.ego, self.stamp()))  # the terminal state
        self.pub_result.publish(st)
        self.outcomes.append((res.outcome, res.steps))
        if self.scenarios:
            self.start_next()


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory):
    from bimacppo_learning.checkpoint import export_policy
    from bimacppo_learning.ppo import PPO
    path = tmp_path_factory.mktemp("policy") / "policy.pt"
    export_policy(PPO(16, (5, 5, 3), seed=POLICY_SEED), path)
    return path


def _planner_and_controller(policy_file):
    """Real planner and controller nodes on sim time, as a world-less graph runs them."""
    from bimacppo_mpc.ros.controller_node import ControllerNode
    from bimacppo_planner.ros.planner_node import PlannerNode

    sim = Parameter("use_sim_time", value=True)
    planner = PlannerNode(parameter_overrides=[Parameter("policy_path", value=str(policy_file)),
                                               Parameter("map_id", value=MAP), sim])
    return planner, ControllerNode(parameter_overrides=[sim])


def test_planner_and_controller_answer_a_plain_publisher(policy_file):
    rclpy.init()
    nodes, ex = [], SingleThreadedExecutor()
    try:
        planner, ctrl = _planner_and_controller(policy_file)
        world = ScriptedWorld(EPISODES)
        probe = Node("probe")
        returns = []
        probe.create_subscription(I.DiagnosticStatus, I.TOPIC_PLANNER_RESULT,
                                  lambda m: returns.append(I.status_to_result(m)), I.RESULT_QOS)
        nodes = [planner, ctrl, world, probe]
        for n in nodes:
            ex.add_node(n)
        world.start_next()
        t_end = time.monotonic() + TIMEOUT_S
        while not (world.done and len(returns) == len(EPISODES)) and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()
    assert world.done, f"loop stalled at tick {world.tick}; outcomes so far {world.outcomes}"
    assert len(world.outcomes) == len(EPISODES)
    answered = {s for s, _, _ in world.commands}
    # a command for every tick of both episodes, stamped with that tick's stamp ...
    assert set(world.ticks) <= answered, sorted(set(world.ticks) - answered)[:5]
    # ... and nothing else: with use_sim_time the watchdog follows this source's /clock, which
    # only advances when the loop does, so no safe-stop (stamped with another time) was sent
    assert answered <= set(world.ticks), sorted(answered - set(world.ticks))[:5]
    assert len(world.ticks) == sum(steps for _, steps in world.outcomes)
    for _, u, horizon in world.commands:
        assert np.all(np.isfinite(u)) and np.all(np.isfinite(horizon)) and len(horizon) > 1
    # the planner computed the agent's return for each episode the source ended
    assert [r.outcome for r in returns] == [o for o, _ in world.outcomes]
    assert all(r.episode_return is not None and math.isfinite(r.episode_return) for r in returns)


@pytest.mark.parametrize("scenario", EPISODES)
def test_planner_node_return_is_the_environment_return(policy_file, scenario):
    """``planner_node.episode_return`` (what /planner/episode_result carries) summed over an
    ``IntersectionEnv`` episode driven by the same policy equals the env's own return."""
    from bimacppo_planner.agent import load_policy
    from bimacppo_learning.env import IntersectionEnv
    from bimacppo_planner.ros.planner_node import episode_return
    env = IntersectionEnv(MAP)
    policy = load_policy(policy_file)
    obs, _ = env.reset(options={"n_sv": scenario.n_sv, "task": scenario.task, "scenario_seed": scenario.seed})
    flags, done, info = [], False, {}
    while not done:
        obs, _, term, trunc, info = env.step(policy.act(obs, deterministic=True))
        flags.append(info["lane_change"])
        done = term or trunc
    facts = {"n_sv": str(info["n_sv"]), "n_pcp": str(info["n_pcp"]),   # as the world's result carries them
             "speed": repr(float(env.world.ego[2])), "dist_to_goal": repr(float(env.world.dist_to_goal()))}
    assert episode_return(flags, info["outcome"], facts, env.cfg.reward) == pytest.approx(info["episode_return"],
                                                                                          abs=1e-9)
    with pytest.raises(KeyError):
        episode_return(flags, info["outcome"], {k: v for k, v in facts.items() if k != "speed"}, env.cfg.reward)
    with pytest.raises(ValueError, match="no decision"):
        episode_return([], info["outcome"], facts, env.cfg.reward)


def test_planner_node_policy_selection(tmp_path):
    """No policy_path: the policy shipped in bimacppo_planner; a bad path: one clear error."""
    from bimacppo_planner.agent import shipped_policy_path
    from bimacppo_planner.ros.planner_node import PlannerNode
    rclpy.init()
    try:
        with pytest.raises(ValueError, match="nope.pt"):
            PlannerNode(parameter_overrides=[Parameter("policy_path", value=str(tmp_path / "nope.pt"))])
        if shipped_policy_path().is_file():
            node = PlannerNode()
            assert node.hp.policy.path == str(shipped_policy_path())
            node.destroy_node()
    finally:
        rclpy.try_shutdown()
