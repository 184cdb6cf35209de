"""The world node's goal re-send (docs/ros.md): a reader that missed the latched goal gets
it again while the episode runs, with the episode's stamp, so it is a repeat and not a new
episode. Real world node, real DDS, one executor."""
import time

import pytest

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402

from bimacppo_interfaces import contract as I  # noqa: E402


def _goals_received(period_s: float, listen_s: float) -> list:
    """Stamps of every /goal_pose a late, volatile reader gets from a lockstep world that
    nobody answers (its episode stays at the first tick)."""
    from bimacppo_sim.ros.world_node import WorldNode

    rclpy.init()
    ex = SingleThreadedExecutor()
    nodes = []
    try:
        world = WorldNode(parameter_overrides=[Parameter("goal_resend_period_s", value=period_s),
                                               Parameter("scenario.n_sv", value=1)])
        probe = Node("goal_probe")
        stamps = []
        volatile = I.QoSProfile(depth=10)   # no latched sample: only what is published from now on
        probe.create_subscription(I.PoseStamped, I.TOPIC_GOAL,
                                  lambda m: stamps.append(I.stamp_to_ns(m.header.stamp)), volatile)
        nodes = [world, probe]
        for n in nodes:
            ex.add_node(n)
        t_end = time.monotonic() + listen_s
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.02)
        assert world.active and world.episodes == 0
        return stamps, world.stamp_ns()
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()


def test_world_resends_the_running_goal_with_its_stamp():
    stamps, first_tick = _goals_received(0.2, 2.0)
    assert len(stamps) >= 4, stamps       # ~9 expected in 2 s; a loaded box may lose a few
    assert set(stamps) == {first_tick}    # the episode's stamp: a repeat, not a new episode


def test_goal_resend_can_be_switched_off():
    stamps, _ = _goals_received(0.0, 1.5)
    assert stamps == []                   # only the latched sample, which this reader does not take


def test_run_time_parameter_changes_are_applied_or_refused_with_a_reason():
    """scenario.* change at run time (the curriculum's channel); everything else is read at
    start-up and declared read-only, so rclpy refuses a change with a reason instead of the
    node accepting and ignoring it."""
    from bimacppo_sim.ros.world_node import WorldNode

    rclpy.init()
    try:
        world = WorldNode()
        ok = world.set_parameters([Parameter("scenario.n_sv", value=2)])[0]
        assert ok.successful and world.get_parameter("scenario.n_sv").value == 2
        bad = world.set_parameters([Parameter("scenario.n_sv", value=9)])[0]
        assert not bad.successful and "n_sv" in bad.reason
        for name, value in (("rate_factor", -5.0), ("rate_factor", 2.0), ("mode", "realtime")):
            res = world.set_parameters([Parameter(name, value=value)])[0]
            assert not res.successful and "read-only" in res.reason, (name, res.reason)
        assert world.get_parameter("rate_factor").value != -5.0
        world.destroy_node()
    finally:
        rclpy.try_shutdown()


def test_world_offers_its_maps_tasks_and_refuses_the_others():
    """map_tasks tells a client (the curriculum) which tasks the map has; a task the map lacks
    is refused when set, with a reason naming them, and map_tasks itself cannot be set."""
    from bimacppo_common.conventions import TASKS
    from bimacppo_ros_common.params import ConfigError
    from bimacppo_sim.ros.world_node import WorldNode

    rclpy.init()
    try:
        road = WorldNode(parameter_overrides=[Parameter("map_id", value="three_lane_straight"),
                                              Parameter("autostart", value=False)])
        assert road.get_parameter("map_tasks").value == ["straight"]
        bad = road.set_parameters([Parameter("scenario.task", value="left")])[0]
        assert not bad.successful and "map_tasks: straight" in bad.reason, bad.reason
        assert road.set_parameters([Parameter("scenario.task", value="straight")])[0].successful
        road.destroy_node()
        junction = WorldNode(parameter_overrides=[Parameter("autostart", value=False)])
        assert junction.get_parameter("map_tasks").value == list(TASKS)
        assert junction.set_parameters([Parameter("scenario.task", value="left")])[0].successful
        junction.destroy_node()
        with pytest.raises(ConfigError, match="map_tasks comes from the map"):
            WorldNode(parameter_overrides=[Parameter("map_tasks", value=["left"])])
        with pytest.raises(ValueError, match="not available on map 'three_lane_straight'"):
            WorldNode(parameter_overrides=[Parameter("map_id", value="three_lane_straight"),
                                           Parameter("scenario.task", value="right")])
    finally:
        rclpy.try_shutdown()


def test_world_slows_the_svs_evaluation_slows_for_the_same_seed():
    """scenario.slow_svs (the overtaking protocol) makes each reset slow draw_n_slow(seed, n_sv,
    slow_svs) SVs, the number training and evaluation draw for that seed, so the node's episode is
    the in-process world's SV for SV; the reset says how many; a negative value is refused at
    start-up and at run time, and 0 (the default) slows none."""
    from std_srvs.srv import Trigger

    from bimacppo_learning.seed_sets import eval_seed
    from bimacppo_ros_common.params import ConfigError
    from bimacppo_sim import Scenario, World, draw_n_slow, load_map
    from bimacppo_sim.ros.world_node import WorldNode

    rclpy.init()
    try:
        node = WorldNode(parameter_overrides=[Parameter("map_id", value="three_lane_straight"),
                                              Parameter("autostart", value=False),
                                              Parameter("scenario.n_sv", value=3),
                                              Parameter("scenario.slow_svs", value=2)])
        ref = World(load_map("three_lane_straight"))
        drawn = []
        for k in range(12):
            seed = eval_seed(1, 3, k, "validation")
            assert node.set_parameters([Parameter("scenario.seed", value=seed)])[0].successful
            resp = node._on_reset(Trigger.Request(), Trigger.Response())
            n_slow = draw_n_slow(seed, 3, 2)
            assert resp.success and f"n_slow={n_slow}" in resp.message, resp.message
            ref.reset(Scenario(n_sv=3, task="straight", seed=seed, n_slow=n_slow))
            assert [(sv.slow, sv.v_des) for sv in node.world.svs] == [(sv.slow, sv.v_des) for sv in ref.svs]
            assert sum(sv.slow for sv in node.world.svs) == n_slow
            drawn.append(n_slow)
        assert set(drawn) == {0, 1, 2}                      # the draw varies with the seed
        bad = node.set_parameters([Parameter("scenario.slow_svs", value=-1)])[0]
        assert not bad.successful and node.get_parameter("scenario.slow_svs").value == 2
        assert node.set_parameters([Parameter("scenario.slow_svs", value=0)])[0].successful
        node._on_reset(Trigger.Request(), Trigger.Response())
        assert not any(sv.slow for sv in node.world.svs)
        node.destroy_node()
        with pytest.raises(ConfigError, match="scenario.slow_svs"):
            WorldNode(parameter_overrides=[Parameter("scenario.slow_svs", value=-2)])
    finally:
        rclpy.try_shutdown()


def test_realtime_world_never_applies_a_command_stamped_in_the_future():
    """Commands with a = +3 stamped far ahead (then none): the world drops them and brakes; it
    must not accelerate the EV until the episode ends."""
    from bimacppo_sim.ros.world_node import WorldNode

    rclpy.init()
    ex = SingleThreadedExecutor()
    nodes = []
    try:
        world = WorldNode(parameter_overrides=[Parameter("mode", value="realtime"),
                                               Parameter("rate_factor", value=1.0),
                                               Parameter("scenario.n_sv", value=0)])
        pub_node = Node("future_commands")
        pub = pub_node.create_publisher(I.JointTrajectory, I.TOPIC_COMMAND, I.STATE_QOS)
        nodes = [world, pub_node]
        for n in nodes:
            ex.add_node(n)
        v0 = float(world.world.ego[2])
        assert v0 > 0.5                      # the EV starts moving: acceleration would show
        far = (2 ** 31 - 1) * I.NS_PER_S
        speeds = []
        t_end = time.monotonic() + 2.0
        k = 0
        while time.monotonic() < t_end:
            if k < 30:                       # a burst of future commands, then none
                pub.publish(I.command_to_trajectory([3.0, 0.0], far - k))
                k += 1
            ex.spin_once(timeout_sec=0.01)
            speeds.append(float(world.world.ego[2]))
        assert world.dropped.get(I.TOPIC_COMMAND, 0) >= 1
        assert max(speeds) <= v0 + 1e-9 and speeds[-1] < v0, (v0, max(speeds), speeds[-1])
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()


def test_world_with_a_posed_map_publishes_in_the_map_frame(tmp_path):
    """A map file's pose moves what the world publishes (EV, SVs, goal), not its simulation."""
    import math

    import numpy as np
    import yaml

    from bimacppo_sim.road import MAP_DIR
    from bimacppo_sim.ros.world_node import WorldNode

    spec = yaml.safe_load((MAP_DIR / "dual_lane_4way.yaml").read_text())
    spec["pose"] = {"x": -250.0, "y": 730.0, "heading": -2.0}
    path = tmp_path / "posed.yaml"
    path.write_text(yaml.safe_dump(spec))
    rclpy.init()
    ex = SingleThreadedExecutor()
    nodes = []
    try:
        world = WorldNode(parameter_overrides=[Parameter("map_id", value=str(path)),
                                               Parameter("scenario.n_sv", value=2)])
        probe = Node("posed_probe")
        got = {}
        probe.create_subscription(I.Odometry, I.TOPIC_EGO_ODOM, lambda m: got.setdefault("odom", m), I.STATE_QOS)
        probe.create_subscription(I.MultiDOFJointTrajectory, I.TOPIC_OBJECTS,
                                  lambda m: got.setdefault("objects", m), I.STATE_QOS)
        probe.create_subscription(I.PoseStamped, I.TOPIC_GOAL, lambda m: got.setdefault("goal", m), I.LATCHED_QOS)
        nodes = [world, probe]
        for n in nodes:
            ex.add_node(n)
        t_end = time.monotonic() + 10.0
        while len(got) < 3 and time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.02)
        assert len(got) == 3, sorted(got)
        f = world.world.road.frame
        ego = I.odometry_to_state(got["odom"])
        assert np.allclose(f.states_to_map(ego), world.world.ego, atol=1e-9)
        assert math.hypot(ego[0] + 250.0, ego[1] - 730.0) < 100.0    # near the posed junction
        _, svs = I.objects_to_svs(got["objects"])
        assert np.allclose(f.states_to_map(svs), np.asarray(world.world.sv_states()).reshape(-1, 4), atol=1e-9)
        assert np.allclose(f.poses_to_map(I.pose_to_goal(got["goal"])), world.world.goal, atol=1e-9)
    finally:
        for n in nodes:
            n.destroy_node()
        rclpy.try_shutdown()


def test_world_runs_never_go_back_in_time(tmp_path):
    """Each world run starts after every stamp the earlier runs in its domain sent (the run
    clock's lease); ``clock_file:=none`` starts at one tick. Realtime worlds, so the runs
    publish ticks without anyone answering."""
    from bimacppo_ros_common.run_clock import LEASE_S
    from bimacppo_sim.ros.world_node import WorldNode

    lease = tmp_path / "clock"

    def one_run(clock_file, seconds=0.6):
        world = WorldNode(parameter_overrides=[Parameter("mode", value="realtime"),
                                               Parameter("rate_factor", value=20.0),
                                               Parameter("clock_file", value=clock_file)])
        ex = SingleThreadedExecutor()
        ex.add_node(world)
        first = world.stamp_ns()
        t_end = time.monotonic() + seconds
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.01)
        last = world.stamp_ns()
        ex.shutdown()
        world.destroy_node()
        return first, last

    rclpy.init()
    try:
        runs = [one_run(str(lease)) for _ in range(3)]
        fresh = one_run("none")
    finally:
        rclpy.try_shutdown()
    assert runs[0][0] == 100_000_000 and all(last > first for first, last in runs), runs
    for (_, last), (first, _) in zip(runs, runs[1:]):
        assert last < first <= last + int((LEASE_S + 0.1) * I.NS_PER_S) + 100_000_000, runs
    assert fresh[0] == 100_000_000
