"""Message <-> numpy conventions (bimacppo_interfaces.contract) and MCAP helpers: pure, fast."""
import math

import numpy as np
import pytest

pytest.importorskip("rclpy")

from bimacppo_bag import mcap_io  # noqa: E402
from bimacppo_common.conventions import wrap_angle  # noqa: E402
from bimacppo_interfaces import contract as I  # noqa: E402

RNG = np.random.default_rng(0)


def _random_states(n):
    s = RNG.uniform(-50, 50, size=(n, 4))
    s[:, 2] = RNG.uniform(-2, 15, size=n)
    s[:, 3] = RNG.uniform(-math.pi, math.pi, size=n)
    return s


@pytest.mark.parametrize("psi", [0.0, 0.3, -2.9, math.pi, -math.pi + 1e-9, 3 * math.pi / 2])
def test_state_round_trip_and_yaw_convention(psi):
    state = np.array([12.5, -3.25, 4.0, psi])
    msg = I.state_to_odometry(state, 1_500_000_000)
    assert msg.header.frame_id == "map" and msg.child_frame_id == "base_link"
    assert msg.header.stamp.sec == 1 and msg.header.stamp.nanosec == 500_000_000
    assert msg.twist.twist.linear.x == 4.0
    back = I.odometry_to_state(msg)
    assert np.allclose(back[:3], state[:3], atol=0, rtol=0)
    assert abs(wrap_angle(back[3] - psi)) < 1e-12
    assert -math.pi < back[3] <= math.pi


def test_yaw_is_counter_clockwise_from_x():
    q = I.yaw_to_quaternion(math.pi / 2)  # facing +y (north)
    assert q.z > 0 and abs(q.w - q.z) < 1e-12
    assert I.quaternion_to_yaw(q) == pytest.approx(math.pi / 2)


def test_odometry_validation_errors():
    msg = I.state_to_odometry([0, 0, 1, 0], 0)
    msg.header.frame_id = "odom"
    with pytest.raises(I.MessageError, match="frame_id"):
        I.odometry_to_state(msg)
    msg = I.state_to_odometry([0, 0, 1, 0], 0)
    msg.pose.pose.position.x = float("nan")
    with pytest.raises(I.MessageError, match="non-finite"):
        I.odometry_to_state(msg)
    msg = I.state_to_odometry([0, 0, 1, 0], 0)
    msg.pose.pose.orientation.w = 0.0  # |q| = 0
    with pytest.raises(I.MessageError, match="normalised"):
        I.odometry_to_state(msg)
    with pytest.raises(I.MessageError, match="non-finite"):
        I.state_to_odometry([0, 0, float("inf"), 0], 0)
    with pytest.raises(I.MessageError, match="shape"):
        I.state_to_odometry([0, 0, 1], 0)
    with pytest.raises(I.MessageError, match="stamp"):
        I.state_to_odometry([0, 0, 1, 0], -1)


@pytest.mark.parametrize("n", [0, 1, 3])
def test_objects_round_trip(n):
    states = _random_states(n)
    ids = [f"sv{i}" for i in range(n)]
    msg = I.svs_to_objects(ids, states, 42)
    assert len(msg.points) == 1 and len(msg.points[0].transforms) == n
    ids2, back = I.objects_to_svs(msg)
    assert ids2 == ids and back.shape == (n, 4)
    assert np.allclose(back[:, :3], states[:, :3], atol=0, rtol=0)
    assert np.allclose(np.cos(back[:, 3] - states[:, 3]), 1.0, atol=1e-12)


def test_objects_validation_errors():
    with pytest.raises(I.MessageError, match="rows"):
        I.svs_to_objects(["a", "b"], _random_states(3), 0)
    with pytest.raises(I.MessageError, match="unique"):
        I.svs_to_objects(["a", "a"], _random_states(2), 0)
    msg = I.svs_to_objects(["a", "b"], _random_states(2), 0)
    msg.points[0].velocities.pop()
    with pytest.raises(I.MessageError, match="velocities"):
        I.objects_to_svs(msg)
    msg = I.svs_to_objects(["a"], _random_states(1), 0)
    msg.points = []
    with pytest.raises(I.MessageError, match="no trajectory point"):
        I.objects_to_svs(msg)
    msg = I.svs_to_objects(["a"], _random_states(1), 0)
    msg.points[0].velocities[0].linear.x = float("nan")
    with pytest.raises(I.MessageError, match="non-finite"):
        I.objects_to_svs(msg)


def test_command_round_trip_with_horizon_and_joint_order():
    U = np.array([[1.5, -0.2], [0.5, -0.1], [0.0, 0.05]])
    msg = I.command_to_trajectory(U[0], 7, horizon=U, dt=0.1)
    assert msg.joint_names == ["steering", "drive"]
    p0 = msg.points[0]
    assert p0.positions[0] == -0.2 and p0.accelerations[1] == 1.5  # delta and a where DESIGN says
    assert msg.points[2].time_from_start.nanosec == 200_000_000
    u, rows = I.trajectory_to_command(msg)
    assert np.array_equal(u, U[0]) and np.array_equal(rows, U)
    # a producer listing the joints the other way round means the same command
    msg.joint_names = ["drive", "steering"]
    for p in msg.points:
        p.positions = [p.positions[1], p.positions[0]]
        p.accelerations = [p.accelerations[1], p.accelerations[0]]
    u2, _ = I.trajectory_to_command(msg)
    assert np.array_equal(u2, U[0])


def test_command_validation_errors():
    msg = I.command_to_trajectory([1.0, 0.1], 0)
    msg.joint_names = ["steer", "drive"]
    with pytest.raises(I.MessageError, match="joint_names"):
        I.trajectory_to_command(msg)
    msg = I.command_to_trajectory([1.0, 0.1], 0)
    msg.points = []
    with pytest.raises(I.MessageError, match="no trajectory point"):
        I.trajectory_to_command(msg)
    msg = I.command_to_trajectory([1.0, 0.1], 0)
    msg.points[0].accelerations = [0.0]
    with pytest.raises(I.MessageError, match="2 entries"):
        I.trajectory_to_command(msg)
    msg = I.command_to_trajectory([1.0, 0.1], 0)
    msg.points[0].positions = [float("nan"), 0.0]
    with pytest.raises(I.MessageError, match="non-finite"):
        I.trajectory_to_command(msg)
    with pytest.raises(I.MessageError, match="dt"):
        I.command_to_trajectory([1.0, 0.1], 0, horizon=np.zeros((3, 2)))


def test_reference_goal_and_result_round_trip():
    ref = I.reference_to_odometry([1.0, 2.0, 6.0, 0.5], 10)
    assert ref.child_frame_id == "x_imr"
    assert np.allclose(I.odometry_to_reference(ref), [1.0, 2.0, 6.0, 0.5])
    goal = I.goal_to_pose([-30.0, 3.5, math.pi], 10)
    g = I.pose_to_goal(goal)
    assert np.allclose(g[:2], [-30.0, 3.5]) and abs(wrap_angle(g[2] - math.pi)) < 1e-12
    res = I.EpisodeResult("collision", -12.5, 2, "left", 7, 33, 123)
    st = I.result_to_status(res)
    assert st.level == I.DiagnosticStatus.ERROR and st.message == "collision"
    assert I.status_to_result(st) == res
    with pytest.raises(I.MessageError, match="outcome"):
        I.result_to_status(I.EpisodeResult("crash", 0.0, 0, "left", 0, 0))
    st.values = [kv for kv in st.values if kv.key != "steps"]
    with pytest.raises(I.MessageError, match="missing"):
        I.status_to_result(st)


def test_markers_have_one_box_per_vehicle():
    arr = I.world_markers([0, 0, 1, 0], _random_states(2), [10, 0, 0], np.zeros((5, 3)), 0)
    ns = [m.ns for m in arr.markers]
    assert ns.count("sv") == 2 and ns.count("ego") == 1 and "goal" in ns and "route" in ns
    assert arr.markers[0].action == I.Marker.DELETEALL


# ----------------------------------------------------------------------------- MCAP helpers
def test_schema_text_matches_rosbag2_layout():
    text = mcap_io.full_definition("nav_msgs/msg/Odometry")
    parts = text.split("\n" + "=" * 80 + "\n")
    assert "std_msgs/Header header" in parts[0] and "MSG:" not in parts[0]
    names = [p.splitlines()[0] for p in parts[1:]]
    assert all(n.startswith("MSG: ") for n in names)
    deps = [n[5:] for n in names]
    assert len(deps) == len(set(deps))  # each dependency once
    assert {"std_msgs/Header", "builtin_interfaces/Time", "geometry_msgs/Quaternion"} <= set(deps)
    # an independent parser (mcap_ros2) builds a decoder from it
    from mcap_ros2._dynamic import generate_dynamic
    decoders = generate_dynamic("nav_msgs/msg/Odometry", text)
    assert "nav_msgs/msg/Odometry" in decoders or "nav_msgs/Odometry" in decoders


def test_schema_for_unknown_type_is_a_clear_error():
    with pytest.raises(mcap_io.DefinitionNotFound, match="no_such_msgs/msg/Foo"):
        mcap_io.full_definition("no_such_msgs/msg/Foo")
    with pytest.raises(mcap_io.DefinitionNotFound, match="not a ROS message type"):
        mcap_io.full_definition("Odometry")


def test_qos_yaml_round_trip_and_legacy_integers():
    recs = [mcap_io.QosRecord(depth=1, durability="transient_local"),
            mcap_io.QosRecord(reliability="best_effort", deadline_ns=2_500_000_000)]
    text = mcap_io.qos_to_yaml(recs)
    assert "durability: transient_local" in text and "sec: 9223372036" in text
    assert mcap_io.qos_from_yaml(text) == recs
    legacy = "- history: 1\n  depth: 5\n  reliability: 2\n  durability: 1\n  liveliness: 1\n"
    (r,) = mcap_io.qos_from_yaml(legacy)
    assert (r.reliability, r.durability, r.depth) == ("best_effort", "transient_local", 5)
    assert mcap_io.qos_from_yaml(":: not yaml [") == []


def test_objects_without_svs_may_have_no_point():
    """No SVs: no joint names, with one empty point (what the world sends) or none at all."""
    for points in ([I.MultiDOFJointTrajectoryPoint()], []):
        msg = I.svs_to_objects([], np.zeros((0, 4)), 7)
        msg.points = points
        ids, states = I.objects_to_svs(msg)
        assert ids == [] and states.shape == (0, 4)
    msg = I.svs_to_objects(["a"], _random_states(1), 7)
    msg.points = []
    with pytest.raises(I.MessageError, match="1 joint_names but no trajectory point"):
        I.objects_to_svs(msg)


def test_results_with_a_non_finite_fact_are_refused():
    st = I.result_to_status(I.EpisodeResult("timeout", None, 1, "left", 3, 10, 5))
    st.values += [I.KeyValue(key="dist_to_goal", value="2.5"), I.KeyValue(key="collided_with", value="sv_1")]
    assert I.status_to_result(st).n_sv == 1
    for bad in ("nan", "inf", "-Infinity"):
        st2 = I.DiagnosticStatus(name=st.name, values=list(st.values) + [I.KeyValue(key="speed", value=bad)])
        with pytest.raises(I.MessageError, match="speed is not finite"):
            I.status_to_result(st2)
