"""The stack's ROS interface contract in code: names, QoS and message <-> numpy conversion.

docs/interfaces.md is the prose version of this module; the two must agree. Every
node converts through these functions so that a convention (frame, sign, field) is
decided exactly once. Converters reject anything they cannot map unambiguously with
a :class:`MessageError` instead of guessing, because a silently wrong array (NaN
state, swapped joints, mismatched lengths) would drive the vehicle on garbage.

Only standard message types are used: custom .msg packages do not build
on the pip-installed ROS here, and standard types are what lets another source
(another simulator, a bridge, a recorded drive) replace the world node.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, Mapping, Optional, Sequence

import numpy as np
from builtin_interfaces.msg import Duration as DurationMsg
from builtin_interfaces.msg import Time as TimeMsg
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue
from geometry_msgs.msg import Point, PoseStamped, Quaternion, Transform, Twist
from nav_msgs.msg import Odometry
from rosgraph_msgs.msg import Clock as ClockMsg  # noqa: F401 - re-exported for the nodes
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from trajectory_msgs.msg import (
    JointTrajectory,
    JointTrajectoryPoint,
    MultiDOFJointTrajectory,
    MultiDOFJointTrajectoryPoint,
)
from visualization_msgs.msg import Marker, MarkerArray

from bimacppo_common.conventions import OUTCOMES, wrap_angle

# ----------------------------------------------------------------------------- names
FRAME_MAP = "map"
FRAME_BASE = "base_link"
FRAME_REFERENCE = "x_imr"

TOPIC_CLOCK = "/clock"
TOPIC_EGO_ODOM = "/ego/odom"
TOPIC_OBJECTS = "/objects"
TOPIC_MARKERS = "/objects/markers"
TOPIC_GOAL = "/goal_pose"
TOPIC_REFERENCE = "/planner/reference"
TOPIC_PLANNER_MARKERS = "/planner/markers"
TOPIC_COMMAND = "/control/command"
TOPIC_RESULT = "/episode/result"
TOPIC_PLANNER_RESULT = "/planner/episode_result"
# The documented type of every topic of the contract (docs/interfaces.md): what a reader
# subscribes with, and what the recorder records when a topic is offered with several types.
TOPIC_TYPES = {
    TOPIC_CLOCK: "rosgraph_msgs/msg/Clock",
    TOPIC_EGO_ODOM: "nav_msgs/msg/Odometry",
    TOPIC_OBJECTS: "trajectory_msgs/msg/MultiDOFJointTrajectory",
    TOPIC_MARKERS: "visualization_msgs/msg/MarkerArray",
    TOPIC_GOAL: "geometry_msgs/msg/PoseStamped",
    TOPIC_REFERENCE: "nav_msgs/msg/Odometry",
    TOPIC_PLANNER_MARKERS: "visualization_msgs/msg/MarkerArray",
    TOPIC_COMMAND: "trajectory_msgs/msg/JointTrajectory",
    TOPIC_RESULT: "diagnostic_msgs/msg/DiagnosticStatus",
    TOPIC_PLANNER_RESULT: "diagnostic_msgs/msg/DiagnosticStatus",
}

SRV_WORLD_RESET = "/world/reset"
SRV_WORLD_SET_PARAMETERS = "/world/set_parameters"
SRV_CURRICULUM_NEXT = "/curriculum/next"

WORLD_NODE = "world"
PLANNER_NODE = "planner"
CONTROLLER_NODE = "controller"
CURRICULUM_NODE = "curriculum"
RECORDER_NODE = "mcap_recorder"
PLAYER_NODE = "mcap_player"

JOINT_STEERING = "steering"
JOINT_DRIVE = "drive"
COMMAND_JOINTS = (JOINT_STEERING, JOINT_DRIVE)

RESULT_NAME = "bimacppo/episode"
RESULT_LEVEL = {"success": DiagnosticStatus.OK, "timeout": DiagnosticStatus.WARN,
                "collision": DiagnosticStatus.ERROR}

NS_PER_S = 1_000_000_000

# ----------------------------------------------------------------------------- QoS
# Reliable everywhere: lockstep waits for one specific message per tick, so a dropped
# sample would stall the loop (best effort buys nothing on localhost). A reliable
# publisher also matches best-effort subscribers (rclpy's /clock subscription, RViz
# "best effort" displays), never the other way round.
STATE_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
"""/ego/odom, /objects, /planner/reference, /control/command."""

LATCHED_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1,
                         reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
"""/goal_pose: a late-joining planner (or recorder) still gets the current goal."""

RESULT_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=50,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
"""/episode/result: volatile, so a late curriculum never learns from old episodes twice."""

CLOCK_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=10,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)

MARKER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=5,
                        reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)

# The documented profile of every topic of the contract (docs/interfaces.md, "QoS profiles"),
# next to TOPIC_TYPES: what a source re-offers when it has no record of the publishers' QoS
# (the MCAP player on a bag written without rosbag2's offered_qos_profiles).
TOPIC_QOS = {
    TOPIC_CLOCK: CLOCK_QOS,
    TOPIC_EGO_ODOM: STATE_QOS,
    TOPIC_OBJECTS: STATE_QOS,
    TOPIC_MARKERS: MARKER_QOS,
    TOPIC_GOAL: LATCHED_QOS,
    TOPIC_REFERENCE: STATE_QOS,
    TOPIC_PLANNER_MARKERS: MARKER_QOS,
    TOPIC_COMMAND: STATE_QOS,
    TOPIC_RESULT: RESULT_QOS,
    TOPIC_PLANNER_RESULT: RESULT_QOS,
}


class MessageError(ValueError):
    """A message that cannot be converted without guessing (names the topic field at fault)."""


# ----------------------------------------------------------------------------- helpers
def ns_to_stamp(ns: int) -> TimeMsg:
    ns = int(ns)
    if ns < 0:
        raise MessageError(f"stamp must be >= 0 ns, got {ns}")
    return TimeMsg(sec=ns // NS_PER_S, nanosec=ns % NS_PER_S)


def stamp_to_ns(stamp: TimeMsg) -> int:
    """Stamp -> ns; a negative time or nanosec >= 1 s is not a stamp any source here sends."""
    if stamp.sec < 0 or stamp.nanosec >= NS_PER_S:
        raise MessageError(f"invalid stamp sec={stamp.sec} nanosec={stamp.nanosec}")
    return int(stamp.sec) * NS_PER_S + int(stamp.nanosec)


def ns_to_duration(ns: int) -> DurationMsg:
    ns = int(ns)
    return DurationMsg(sec=ns // NS_PER_S, nanosec=ns % NS_PER_S)


def yaw_to_quaternion(yaw: float) -> Quaternion:
    return Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


QUAT_NORM_TOL = 1e-3
"""Normalisation slack for incoming quaternions: float32 producers (RViz, bridges) are off by ~1e-7."""


def quaternion_to_yaw(q: Quaternion, where: str = "orientation") -> float:
    vals = (q.x, q.y, q.z, q.w)
    if not all(math.isfinite(v) for v in vals):
        raise MessageError(f"{where}: non-finite quaternion {vals}")
    norm = math.sqrt(sum(v * v for v in vals))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise MessageError(f"{where}: quaternion not normalised (|q| = {norm:.6g})")
    x, y, z, w = (v / norm for v in vals)
    return wrap_angle(math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z)))


def _finite_vector(values, n: int, what: str) -> np.ndarray:
    try:
        arr = np.asarray(values, dtype=float)
    except (TypeError, ValueError) as exc:
        raise MessageError(f"{what}: not numeric ({exc})") from None
    if arr.shape != (n,):
        raise MessageError(f"{what}: expected shape ({n},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise MessageError(f"{what}: non-finite value in {arr.tolist()}")
    return arr


def _check_frame(header, expected: str, what: str) -> None:
    if header.frame_id != expected:
        raise MessageError(f"{what}: header.frame_id is {header.frame_id!r}, expected {expected!r}")


def _check_finite(values: Iterable[float], what: str) -> None:
    vals = list(values)
    if not all(math.isfinite(v) for v in vals):
        raise MessageError(f"{what}: non-finite value in {vals}")


# Plausibility bounds of incoming states (docs/faults.md). Finite is not enough: 1e30 m
# passes isfinite but overflows the MPC's cost (x**2) to inf and the policy's
# normalised observation to garbage. The bounds are far outside anything real (maps
# span ~100 m, v_max is 10 m/s) so they only ever reject broken senders; inputs
# (commands) are not bounded here because the world clips them to the vehicle's limits.
MAX_ABS_COORD_M = 1.0e4
MAX_ABS_SPEED_MPS = 100.0


def _check_plausible(x: float, y: float, v: float, what: str) -> None:
    _check_finite((x, y, v), what)
    if abs(x) > MAX_ABS_COORD_M or abs(y) > MAX_ABS_COORD_M:
        raise MessageError(f"{what}: position ({x:.6g}, {y:.6g}) beyond +-{MAX_ABS_COORD_M:g} m")
    if abs(v) > MAX_ABS_SPEED_MPS:
        raise MessageError(f"{what}: speed {v:.6g} beyond +-{MAX_ABS_SPEED_MPS:g} m/s")


# ----------------------------------------------------------------------------- state
def state_to_odometry(state, stamp_ns: int, frame_id: str = FRAME_MAP,
                      child_frame_id: str = FRAME_BASE) -> Odometry:
    """[x, y, v, psi] -> Odometry: pose in ``map``, twist in the body frame (linear.x = speed)."""
    x, y, v, psi = _finite_vector(state, 4, "state [x, y, v, psi]")
    msg = Odometry()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    msg.pose.pose.position = Point(x=float(x), y=float(y), z=0.0)
    msg.pose.pose.orientation = yaw_to_quaternion(float(psi))
    msg.twist.twist.linear.x = float(v)
    return msg


def odometry_to_state(msg: Odometry, frame_id: str = FRAME_MAP, what: str = "odometry") -> np.ndarray:
    """Odometry -> [x, y, v, psi]; the speed is twist.linear.x (body frame, signed)."""
    _check_frame(msg.header, frame_id, what)
    p = msg.pose.pose.position
    v = msg.twist.twist.linear.x
    _check_plausible(p.x, p.y, v, f"{what} position/speed")
    stamp_to_ns(msg.header.stamp)
    psi = quaternion_to_yaw(msg.pose.pose.orientation, f"{what} orientation")
    return np.array([p.x, p.y, v, psi], dtype=float)


def reference_to_odometry(x_imr, stamp_ns: int) -> Odometry:
    """x_IMR [x, y, v, psi] -> Odometry (child frame ``x_imr``: the reference's own frame)."""
    return state_to_odometry(x_imr, stamp_ns, FRAME_MAP, FRAME_REFERENCE)


def odometry_to_reference(msg: Odometry) -> np.ndarray:
    return odometry_to_state(msg, FRAME_MAP, what="reference")


# ----------------------------------------------------------------------------- SVs
def svs_to_objects(ids: Sequence[str], states, stamp_ns: int,
                   frame_id: str = FRAME_MAP) -> MultiDOFJointTrajectory:
    """SV ids + (n, 4) states -> one MultiDOFJointTrajectory point (n may be 0)."""
    ids = [str(i) for i in ids]
    arr = np.asarray(states, dtype=float).reshape(-1, 4) if len(ids) == 0 else np.asarray(states, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise MessageError(f"SV states: expected shape (n, 4), got {arr.shape}")
    if arr.shape[0] != len(ids):
        raise MessageError(f"SV states: {arr.shape[0]} rows but {len(ids)} ids")
    if len(set(ids)) != len(ids):
        raise MessageError(f"SV ids not unique: {ids}")
    if not np.all(np.isfinite(arr)):
        raise MessageError("SV states: non-finite value")
    msg = MultiDOFJointTrajectory()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.joint_names = ids
    pt = MultiDOFJointTrajectoryPoint()
    for x, y, v, psi in arr:
        tf = Transform()
        tf.translation.x, tf.translation.y, tf.translation.z = float(x), float(y), 0.0
        tf.rotation = yaw_to_quaternion(float(psi))
        pt.transforms.append(tf)
        tw = Twist()
        tw.linear.x = float(v)
        pt.velocities.append(tw)
    msg.points = [pt]
    return msg


def objects_to_svs(msg: MultiDOFJointTrajectory, frame_id: str = FRAME_MAP):
    """MultiDOFJointTrajectory -> (ids, (n, 4) states). Later points (predictions) are ignored.
    No SVs may come as no joint names with one empty point or with no point at all."""
    _check_frame(msg.header, frame_id, "objects")
    stamp_to_ns(msg.header.stamp)
    if len(msg.points) == 0:
        if len(msg.joint_names) == 0:
            return [], np.zeros((0, 4))
        raise MessageError(f"objects: {len(msg.joint_names)} joint_names but no trajectory point "
                           "(points[0] holds the current SV states)")
    pt = msg.points[0]
    n = len(msg.joint_names)
    if len(pt.transforms) != n or len(pt.velocities) != n:
        raise MessageError(f"objects: {n} joint_names but {len(pt.transforms)} transforms "
                           f"and {len(pt.velocities)} velocities")
    ids = list(msg.joint_names)
    if len(set(ids)) != n:
        raise MessageError(f"objects: SV ids not unique: {ids}")
    out = np.zeros((n, 4))
    for i, (tf, tw) in enumerate(zip(pt.transforms, pt.velocities)):
        _check_plausible(tf.translation.x, tf.translation.y, tw.linear.x, f"objects[{ids[i]}]")
        out[i] = (tf.translation.x, tf.translation.y, tw.linear.x,
                  quaternion_to_yaw(tf.rotation, f"objects[{ids[i]}] rotation"))
    return ids, out


# ----------------------------------------------------------------------------- command
def command_to_trajectory(u, stamp_ns: int, horizon=None, dt: float | None = None) -> JointTrajectory:
    """[a, delta] (+ optional (N, 2) horizon) -> JointTrajectory with joints [steering, drive].

    Point k: positions = [delta_k, 0] (the drive joint has no position), accelerations =
    [0, a_k], time_from_start = k * dt. Point 0 is the input to apply now.
    """
    u = _finite_vector(u, 2, "command [a, delta]")
    rows = [u]
    if horizon is not None:
        h = np.asarray(horizon, dtype=float)
        if h.ndim != 2 or h.shape[1] != 2:
            raise MessageError(f"command horizon: expected shape (N, 2), got {h.shape}")
        if not np.all(np.isfinite(h)):
            raise MessageError("command horizon: non-finite value")
        if len(h) > 1:
            if dt is None or not (dt > 0):
                raise MessageError("command horizon needs dt > 0 for time_from_start")
            rows.extend(h[1:])
    msg = JointTrajectory()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = FRAME_BASE
    msg.joint_names = list(COMMAND_JOINTS)
    for k, (a, delta) in enumerate(rows):
        pt = JointTrajectoryPoint()
        pt.positions = [float(delta), 0.0]
        pt.accelerations = [0.0, float(a)]
        pt.time_from_start = ns_to_duration(round(k * (dt or 0.0) * NS_PER_S))
        msg.points.append(pt)
    return msg


def trajectory_to_command(msg: JointTrajectory):
    """JointTrajectory -> (u = [a, delta] of point 0, (K, 2) all points). Joint order may vary."""
    names = list(msg.joint_names)
    if sorted(names) != sorted(COMMAND_JOINTS) or len(names) != len(COMMAND_JOINTS):
        raise MessageError(f"command: joint_names must be {list(COMMAND_JOINTS)} (any order), got {names}")
    if len(msg.points) == 0:
        raise MessageError("command: no trajectory point")
    i_s, i_d = names.index(JOINT_STEERING), names.index(JOINT_DRIVE)
    rows = []
    for k, pt in enumerate(msg.points):
        if len(pt.positions) != 2 or len(pt.accelerations) != 2:
            raise MessageError(f"command point {k}: positions and accelerations need 2 entries "
                               f"(got {len(pt.positions)}, {len(pt.accelerations)})")
        a, delta = pt.accelerations[i_d], pt.positions[i_s]
        _check_finite((a, delta), f"command point {k}")
        rows.append((a, delta))
    arr = np.array(rows, dtype=float)
    return arr[0].copy(), arr


# ----------------------------------------------------------------------------- goal
def goal_to_pose(goal, stamp_ns: int) -> PoseStamped:
    """[x, y, psi] -> PoseStamped in ``map``."""
    x, y, psi = _finite_vector(goal, 3, "goal [x, y, psi]")
    msg = PoseStamped()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = FRAME_MAP
    msg.pose.position = Point(x=float(x), y=float(y), z=0.0)
    msg.pose.orientation = yaw_to_quaternion(float(psi))
    return msg


def pose_to_goal(msg: PoseStamped) -> np.ndarray:
    _check_frame(msg.header, FRAME_MAP, "goal")
    p = msg.pose.position
    _check_plausible(p.x, p.y, 0.0, "goal position")
    stamp_to_ns(msg.header.stamp)
    return np.array([p.x, p.y, quaternion_to_yaw(msg.pose.orientation, "goal orientation")])


# ----------------------------------------------------------------------------- results
@dataclass(frozen=True)
class EpisodeResult:
    outcome: str
    episode_return: Optional[float]   # None in the world's message: the return is the agent's
    n_sv: int
    task: str
    seed: int
    steps: int
    stamp_ns: int = 0


def result_to_status(res: EpisodeResult) -> DiagnosticStatus:
    if res.outcome not in OUTCOMES:
        raise MessageError(f"episode outcome must be one of {OUTCOMES}, got {res.outcome!r}")
    if res.episode_return is not None and not math.isfinite(res.episode_return):
        raise MessageError(f"episode return is not finite: {res.episode_return}")
    st = DiagnosticStatus()
    st.level = RESULT_LEVEL[res.outcome]
    st.name = RESULT_NAME
    st.message = res.outcome
    st.hardware_id = ""
    kv = {"outcome": res.outcome, "n_sv": str(int(res.n_sv)),
          "task": res.task, "seed": str(int(res.seed)), "steps": str(int(res.steps)),
          "stamp_ns": str(int(res.stamp_ns))}
    if res.episode_return is not None:
        kv["return"] = repr(float(res.episode_return))
    st.values = [KeyValue(key=k, value=v) for k, v in kv.items()]
    return st


def status_to_result(msg: DiagnosticStatus) -> EpisodeResult:
    if msg.name != RESULT_NAME:
        raise MessageError(f"episode result: name is {msg.name!r}, expected {RESULT_NAME!r}")
    kv: Mapping[str, str] = {v.key: v.value for v in msg.values}
    missing = [k for k in ("outcome", "n_sv", "task", "seed", "steps") if k not in kv]
    if missing:
        raise MessageError(f"episode result: missing keys {missing}")
    if kv["outcome"] not in OUTCOMES:
        raise MessageError(f"episode result: outcome {kv['outcome']!r} not in {OUTCOMES}")
    try:
        ret = float(kv["return"]) if "return" in kv else None
        n_sv, seed, steps = int(kv["n_sv"]), int(kv["seed"]), int(kv["steps"])
        stamp = int(kv.get("stamp_ns", "0"))
    except ValueError as exc:
        raise MessageError(f"episode result: bad number ({exc})") from None
    if ret is not None and not math.isfinite(ret):
        raise MessageError(f"episode result: return is not finite ({kv['return']})")
    for k, v in kv.items():   # a fact (speed, dist_to_goal, ...) no return can be computed from
        try:
            bad = not math.isfinite(float(v))
        except ValueError:
            continue   # not a number (task, outcome, an SV id)
        if bad:
            raise MessageError(f"episode result: {k} is not finite ({v})")
    if stamp < 0 or steps < 0 or n_sv < 0:
        raise MessageError(f"episode result: negative stamp_ns/steps/n_sv ({stamp}, {steps}, {n_sv})")
    return EpisodeResult(kv["outcome"], ret, n_sv, kv["task"], seed, steps, stamp)


def result_extras(msg: DiagnosticStatus) -> dict:
    """All key-values of a result message as strings (extra facts beyond EpisodeResult)."""
    return {v.key: v.value for v in msg.values}


# ----------------------------------------------------------------------------- markers
ROUTE_MARKER_NS = "route"
"""Namespace of the world's A* route in /objects/markers (one LINE_STRIP): what a reader
(the live view, a bag's frames) takes the route from."""


@dataclass(frozen=True)
class MarkerStyle:
    """Display-only sizes and colours (RGBA 0..1); bodies come from the simulator's config."""
    length: float = 4.69
    width: float = 1.85
    height: float = 1.5
    ego_rgba: tuple = (0.1, 0.4, 1.0, 0.9)
    sv_rgba: tuple = (1.0, 0.5, 0.1, 0.9)
    goal_rgba: tuple = (0.1, 0.9, 0.2, 0.9)
    route_rgba: tuple = (0.8, 0.8, 0.8, 0.6)
    reference_rgba: tuple = (1.0, 0.1, 0.8, 0.9)
    line_width: float = 0.2


def _color(m: Marker, rgba) -> None:
    m.color.r, m.color.g, m.color.b, m.color.a = (float(c) for c in rgba)


def _box(ns: str, mid: int, state, stamp, style: MarkerStyle, rgba) -> Marker:
    m = Marker()
    m.header.stamp, m.header.frame_id = stamp, FRAME_MAP
    m.ns, m.id, m.type, m.action = ns, mid, Marker.CUBE, Marker.ADD
    m.pose.position = Point(x=float(state[0]), y=float(state[1]), z=0.5 * style.height)
    m.pose.orientation = yaw_to_quaternion(float(state[3]))
    m.scale.x, m.scale.y, m.scale.z = style.length, style.width, style.height
    _color(m, rgba)
    return m


def world_markers(ego, sv_states, goal, route, stamp_ns: int,
                  style: MarkerStyle = MarkerStyle()) -> MarkerArray:
    """EV, SVs, goal and A* route; starts with DELETEALL so vanished SVs disappear."""
    stamp = ns_to_stamp(stamp_ns)
    arr = MarkerArray()
    clear = Marker()
    clear.header.stamp, clear.header.frame_id, clear.action = stamp, FRAME_MAP, Marker.DELETEALL
    arr.markers.append(clear)
    arr.markers.append(_box("ego", 0, ego, stamp, style, style.ego_rgba))
    for i, s in enumerate(np.asarray(sv_states, dtype=float).reshape(-1, 4)):
        arr.markers.append(_box("sv", i, s, stamp, style, style.sv_rgba))
    if goal is not None:
        g = Marker()
        g.header.stamp, g.header.frame_id = stamp, FRAME_MAP
        g.ns, g.id, g.type, g.action = "goal", 0, Marker.ARROW, Marker.ADD
        g.pose.position = Point(x=float(goal[0]), y=float(goal[1]), z=0.1)
        g.pose.orientation = yaw_to_quaternion(float(goal[2]))
        g.scale.x, g.scale.y, g.scale.z = 3.0, 0.6, 0.6
        _color(g, style.goal_rgba)
        arr.markers.append(g)
    if route is not None and len(route) > 1:
        r = Marker()
        r.header.stamp, r.header.frame_id = stamp, FRAME_MAP
        r.ns, r.id, r.type, r.action = ROUTE_MARKER_NS, 0, Marker.LINE_STRIP, Marker.ADD
        r.pose.orientation.w = 1.0
        r.scale.x = style.line_width
        r.points = [Point(x=float(p[0]), y=float(p[1]), z=0.05) for p in np.asarray(route)]
        _color(r, style.route_rgba)
        arr.markers.append(r)
    return arr


def reference_markers(x_imr, stamp_ns: int, style: MarkerStyle = MarkerStyle()) -> MarkerArray:
    """x_IMR as an arrow whose length is the reference speed (at least 1 m, to stay visible)."""
    stamp = ns_to_stamp(stamp_ns)
    m = Marker()
    m.header.stamp, m.header.frame_id = stamp, FRAME_MAP
    m.ns, m.id, m.type, m.action = "x_imr", 0, Marker.ARROW, Marker.ADD
    m.pose.position = Point(x=float(x_imr[0]), y=float(x_imr[1]), z=0.2)
    m.pose.orientation = yaw_to_quaternion(float(x_imr[3]))
    m.scale.x, m.scale.y, m.scale.z = max(1.0, float(x_imr[2])), 0.4, 0.4
    _color(m, style.reference_rgba)
    return MarkerArray(markers=[m])


def route_from_markers(markers) -> Optional[np.ndarray]:
    """The world's route in a marker list (``/objects/markers``) as an ``(M, 2)`` array, or None."""
    for mk in markers:
        if mk.ns == ROUTE_MARKER_NS and mk.type == Marker.LINE_STRIP and len(mk.points) >= 2:
            return np.array([[p.x, p.y] for p in mk.points], dtype=float)
    return None
