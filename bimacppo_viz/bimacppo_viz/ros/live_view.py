"""live_view: the running graph on a Foxglove WebSocket server (EV, SVs, route, x_IMR, goal, commands,
episode results with the planner's return).

    ros2 run bimacppo_viz live_view [--ros-args -p port:=8765 -p host:=127.0.0.1 -p map_id:=dual_lane_4way]
    bimacppo-graph --live-view            # the same node inside the one-process graph

Open ``ws://HOST:PORT`` in Foxglove and import the layout ``share/bimacppo_viz/layouts/
bimacppo_live.json`` (docs/live-view.md). The node only listens: every input goes through the
converters of ``bimacppo_interfaces.contract`` with the documented QoS (a reliable reader, so it
matches the graph's publishers; the latched goal reaches it when it starts late), and the scene
is built by :mod:`bimacppo_viz.scene`. A message the converters reject is dropped with a
throttled warning, like in every node. The server binds to ``host`` only (default loopback: a
default must not expose the graph to the network); a port already in use is a one-line error.
"""
from __future__ import annotations

import numpy as np
from rclpy.node import Node
from rclpy.validate_topic_name import validate_topic_name

from bimacppo_interfaces import contract as I
from bimacppo_interfaces.contract import route_from_markers
from bimacppo_ros_common.params import ConfigError, declare
from bimacppo_ros_common.runtime import guarded, one_line, run_single
from bimacppo_sim.config import WorldConfig
from bimacppo_sim.road import available_maps, load_map

from ..scene import CHANNELS, SOURCE_PLANNER, SOURCE_WORLD, LiveScene

NODE_NAME = "live_view"
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765        # Foxglove's default WebSocket port
SERVER_NAME = "bimacppo"
LATCHED_RESEND_S = 1.0     # map and goal are logged again this often: a client joining later gets them

# parameter -> the contract topic it defaults to (a source with other names is remapped here)
TOPIC_PARAMETERS = {
    "ego_topic": I.TOPIC_EGO_ODOM,
    "objects_topic": I.TOPIC_OBJECTS,
    "goal_topic": I.TOPIC_GOAL,
    "reference_topic": I.TOPIC_REFERENCE,
    "command_topic": I.TOPIC_COMMAND,
    "markers_topic": I.TOPIC_MARKERS,
    "result_topic": I.TOPIC_RESULT,
    "planner_result_topic": I.TOPIC_PLANNER_RESULT,
}


def road_lanes(road) -> list:
    """``[(kind, (N, 2) centreline)]`` of a map's lanes in the fixed ``map`` frame: a map file's
    pose places the map's own frame (where its geometry is built) there, as the world publishes."""
    out = []
    for ln in road.lanes.values():
        pts = np.asarray(ln.points, dtype=float)[:, :2]
        out.append((ln.kind, road.frame.poses_to_world(np.c_[pts, np.zeros(len(pts))])[:, :2]))
    return out


class LiveViewNode(Node):
    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        host = str(declare(self, "host", DEFAULT_HOST, "address the WebSocket server binds to (0.0.0.0 = every "
                                                       "interface)")).strip()
        port = declare(self, "port", DEFAULT_PORT, "WebSocket port (0 = any free port, logged at start)",
                       lo=0, hi=65535)
        declare(self, "map_id", "dual_lane_4way", f"map drawn under the scene: {available_maps()} or a YAML path; "
                                                  "'' = none")
        for name, topic in TOPIC_PARAMETERS.items():
            declare(self, name, topic, f"topic read instead of the contract's {topic}")
        g = lambda n: self.get_parameter(n).value  # noqa: E731
        if not host:
            raise ConfigError(f"{NODE_NAME}: parameter host must not be empty")
        topics = {n: str(g(n)) for n in TOPIC_PARAMETERS}
        for name, topic in topics.items():   # before the server binds its port
            try:
                validate_topic_name(topic)
            except Exception as exc:  # noqa: BLE001 - rclpy's InvalidTopicNameException and its kin
                raise ConfigError(f"{NODE_NAME}: parameter {name} {topic!r}: {one_line(exc)}") from None
        map_id = str(g("map_id"))
        road = None
        if map_id:
            try:
                road = load_map(map_id)
            except Exception as exc:  # noqa: BLE001 - YAML syntax, missing keys, wrong types: all user errors
                raise ConfigError(f"{NODE_NAME}: parameter map_id {map_id!r}: {type(exc).__name__}: "
                                  f"{one_line(exc)}") from None
        self.errors: dict = {}

        import foxglove
        veh = WorldConfig.load().vehicle
        self.fox_context = foxglove.Context()
        self.scene = LiveScene(self.fox_context, I.MarkerStyle(length=veh.length, width=veh.width))
        try:
            self.server = foxglove.start_server(name=SERVER_NAME, host=host, port=port, context=self.fox_context)
        except RuntimeError as exc:
            raise ConfigError(f"{NODE_NAME}: cannot serve on {host}:{port}: "
                              f"{one_line(exc).replace('FoxgloveError: ', '')}") from None
        self.url = f"ws://{host}:{self.server.port}"
        if road is not None:
            self.scene.on_road(road_lanes(road))
        self.create_timer(LATCHED_RESEND_S, self.scene.resend_latched)

        def sub(param, msg_type, qos, fn):
            return self.create_subscription(msg_type, topics[param], guarded(self, topics[param], fn, self.errors), qos)

        # the latched goal and the results first: when several are ready at once, the executor
        # serves subscriptions in creation order (docs/interfaces.md, episode boundaries)
        sub("goal_topic", I.PoseStamped, I.LATCHED_QOS, self._goal)
        sub("result_topic", I.DiagnosticStatus, I.RESULT_QOS, self._result)
        sub("planner_result_topic", I.DiagnosticStatus, I.RESULT_QOS, self._planner_result)
        sub("ego_topic", I.Odometry, I.STATE_QOS, self._ego)
        sub("objects_topic", I.MultiDOFJointTrajectory, I.STATE_QOS, self._objects)
        sub("reference_topic", I.Odometry, I.STATE_QOS, self._reference)
        sub("command_topic", I.JointTrajectory, I.STATE_QOS, self._command)
        sub("markers_topic", I.MarkerArray, I.MARKER_QOS, self._markers)
        self.get_logger().info(f"live view on {self.url} (Foxglove: open a WebSocket connection there); "
                               f"channels {', '.join(CHANNELS)}")

    def _ego(self, msg) -> None:
        self.scene.on_state(I.odometry_to_state(msg), I.stamp_to_ns(msg.header.stamp))

    def _objects(self, msg) -> None:
        ids, states = I.objects_to_svs(msg)
        self.scene.on_objects(ids, states, I.stamp_to_ns(msg.header.stamp))

    def _reference(self, msg) -> None:
        self.scene.on_reference(I.odometry_to_reference(msg), I.stamp_to_ns(msg.header.stamp))

    def _goal(self, msg) -> None:
        self.scene.on_goal(I.pose_to_goal(msg), I.stamp_to_ns(msg.header.stamp))

    def _command(self, msg) -> None:
        u, rows = I.trajectory_to_command(msg)
        self.scene.on_command(u, rows, I.stamp_to_ns(msg.header.stamp))

    def _markers(self, msg) -> None:
        route = route_from_markers(msg.markers)
        if route is not None:   # every marker of the array carries the tick's stamp
            self.scene.on_route(route, I.stamp_to_ns(msg.markers[0].header.stamp))

    def _result(self, msg) -> None:
        values = I.result_extras(msg)
        try:
            stamp = int(values.get("stamp_ns", "0"))
        except ValueError:
            raise I.MessageError(f"episode result: stamp_ns is not an integer ({values.get('stamp_ns')!r})") from None
        self.scene.on_result(values, max(stamp, 0), SOURCE_WORLD)

    def _planner_result(self, msg) -> None:
        """The planner's result is the one that carries the return: it is read with the
        contract's converter (return finite, facts well-formed), and one without a return is
        rejected rather than shown as a result without one."""
        res = I.status_to_result(msg)
        if res.episode_return is None:
            raise I.MessageError("planner episode result: no return")
        self.scene.on_result(I.result_extras(msg), res.stamp_ns, SOURCE_PLANNER, res.episode_return)

    def close(self) -> None:
        server = getattr(self, "server", None)
        if server is not None:
            server.stop()
            self.server = None


def main(argv=None) -> int:
    return run_single(lambda _args: LiveViewNode(), argv)


if __name__ == "__main__":
    raise SystemExit(main())
