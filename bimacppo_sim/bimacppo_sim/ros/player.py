"""MCAP player: republishes a recording on its topics, so a recorded drive stands in for the world.

Usage::

    mcap_player run.mcap --ros-args -p rate:=1.0 -p topics:="['/clock','/ego/odom','/objects','/goal_pose']"

``rate`` scales the recorded gaps (2.0 = twice as fast); ``rate:=0.0`` publishes as fast
as the executor allows. ``timing`` picks which gaps: ``log`` (default) the recorded log
times, i.e. the wall pace of the recorded run; ``clock`` the sim time of the recorded
/clock messages, i.e. realtime-style playback (rate 1.0 = one 0.1 s tick per 0.1 s). A
lockstep recording needs ``clock``: its log times are the pace at which that loop
happened to run (often many ticks per 0.1 s), not sim time.

``as_world:=true`` plays exactly the world's outputs (/clock, /ego/odom, /objects,
/objects/markers, /goal_pose, /episode/result) so that live planner and controller nodes
can answer them; the recorded /planner/* and /control/command are then never replayed
(they would compete with the live ones on the same topics).

``wait_subscribers:=N`` holds the start until the /ego/odom publisher has at least N
matched subscribers (every consumer of the world's state reads it: planner and
controller make 2), then waits ``start_delay_s``: a replay is
open loop, and a tick published before the planner and controller are matched is lost
for good (volatile QoS). Stand-in use therefore passes ``wait_subscribers:=2``. Each topic is re-offered with the QoS recorded in its
channel metadata (a latched /goal_pose stays latched). A truncated or corrupt file is
played up to its first unreadable byte and the reason is logged; a missing file or one
without any message is a one-line error, not a traceback.
"""
from __future__ import annotations

import os
import time
from typing import Dict, Optional

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock as ClockMsg

from . import interfaces as I
from . import mcap_io
from .recorder import import_message_type, string_list
from .runtime import run_single

BATCH = 200
"""Messages published per timer callback at most, so the executor stays responsive."""

TIMINGS = ("log", "clock")
WORLD_TOPICS = (I.TOPIC_CLOCK, I.TOPIC_EGO_ODOM, I.TOPIC_OBJECTS, I.TOPIC_MARKERS, I.TOPIC_GOAL,
                I.TOPIC_RESULT)
"""What the world node publishes: the player's topics when it stands in for the world."""
WAIT_TOPIC = I.TOPIC_EGO_ODOM
WAIT_LOG_PERIOD_S = 5.0


def offered_qos(metadata: Dict[str, str], min_depth: int) -> QoSProfile:
    """The QoS to re-offer: the recorded publishers' (if they agree), else reliable/volatile."""
    recs = mcap_io.qos_from_yaml(metadata.get("offered_qos_profiles", ""))
    rel = ReliabilityPolicy.RELIABLE
    dur = DurabilityPolicy.VOLATILE
    depth = min_depth
    if recs:
        if all(r.reliability == "best_effort" for r in recs):
            rel = ReliabilityPolicy.BEST_EFFORT
        if all(r.durability == "transient_local" for r in recs):
            dur = DurabilityPolicy.TRANSIENT_LOCAL
            depth = max(1, max(r.depth for r in recs))
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel, durability=dur)


class McapPlayer(Node):
    """Publishes the messages of one MCAP file at recorded timing (scaled by ``rate``)."""

    def __init__(self, path: Optional[str] = None, **kwargs) -> None:
        super().__init__(I.PLAYER_NODE, **kwargs)
        self.declare_parameter("path", "")
        self.declare_parameter("rate", 1.0)
        self.declare_parameter("start_delay_s", 1.0)
        self.declare_parameter("topics", Parameter.Type.STRING_ARRAY)
        self.declare_parameter("exclude", Parameter.Type.STRING_ARRAY)
        self.declare_parameter("queue_depth", 100)
        self.declare_parameter("period_s", 0.002)
        self.declare_parameter("linger_s", 1.0)
        self.declare_parameter("timing", "log")
        self.declare_parameter("as_world", False)
        self.declare_parameter("wait_subscribers", 0)
        p = self.get_parameter
        self.path = path or p("path").value
        if not self.path:
            raise ValueError("mcap_player: no file given (positional argument or -p path:=FILE.mcap)")
        if not os.path.isfile(self.path):
            raise FileNotFoundError(f"mcap_player: no such file: {self.path}")
        self.rate = float(p("rate").value)
        if not self.rate >= 0.0:
            raise ValueError(f"mcap_player: rate must be >= 0 (0 = as fast as possible), got {self.rate}")
        self.timing = p("timing").value
        if self.timing not in TIMINGS:
            raise ValueError(f"mcap_player: timing must be one of {TIMINGS}, got {self.timing!r}")
        self.topics = set(string_list(self, "topics"))
        if bool(p("as_world").value):
            if self.topics:
                raise ValueError("mcap_player: give either topics or as_world:=true, not both")
            self.topics = set(WORLD_TOPICS)
        if self.timing == "clock" and self.topics and I.TOPIC_CLOCK not in self.topics:
            raise ValueError(f"mcap_player: timing:=clock needs {I.TOPIC_CLOCK} among the played topics")
        self.exclude = set(string_list(self, "exclude"))
        self.depth = int(p("queue_depth").value)
        self.linger_s = float(p("linger_s").value)
        # a first pass finds every channel, so all publishers exist (and get matched during
        # start_delay_s) before the first message goes out: nothing early is lost
        self._pubs: Dict[int, object] = {}
        scan = mcap_io.ReadReport()
        for schema, channel, _ in mcap_io.iter_mcap(self.path, scan, topics=self.topics or None):
            if channel.id not in self._pubs and channel.topic not in self.exclude:
                self._publisher(schema, channel)
        self.report = mcap_io.ReadReport()
        self._it = mcap_io.iter_mcap(self.path, self.report, topics=self.topics or None)
        self._finished_at: Optional[float] = None
        self._pending = None
        self._t0_time: Optional[int] = None
        self._t0_wall: Optional[float] = None
        self.wait_subscribers = int(p("wait_subscribers").value)
        if self.wait_subscribers < 0:
            raise ValueError(f"mcap_player: wait_subscribers must be >= 0, got {self.wait_subscribers}")
        self._start_delay = float(p("start_delay_s").value)
        self._start_at: Optional[float] = None if self.wait_subscribers else time.monotonic() + self._start_delay
        self._waiting_since = time.monotonic()
        if self.wait_subscribers and not any(pb is not None and pb.topic_name == WAIT_TOPIC
                                             for pb in self._pubs.values()):
            raise ValueError(f"mcap_player: wait_subscribers needs {WAIT_TOPIC} among the played topics")
        self.published = 0
        self.done = False
        self.exit_code = 0
        self._timer = self.create_timer(float(p("period_s").value), self._tick,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _publisher(self, schema, channel):
        if channel.id in self._pubs:
            return self._pubs[channel.id]
        pub = None
        if schema is None or channel.message_encoding != mcap_io.MESSAGE_ENCODING:
            self.get_logger().warning(f"{channel.topic}: encoding {channel.message_encoding!r} "
                                      "is not ROS 2 CDR, skipped")
        else:
            try:
                cls = import_message_type(schema.name)
                pub = self.create_publisher(cls, channel.topic, offered_qos(channel.metadata, self.depth))
            except (LookupError, mcap_io.DefinitionNotFound) as exc:
                self.get_logger().warning(f"{channel.topic}: skipped ({exc})")
        self._pubs[channel.id] = pub
        return pub

    def _next(self):
        if self._pending is None:
            try:
                self._pending = next(self._it)
            except StopIteration:
                self._pending = None
        return self._pending

    def _tick(self) -> None:
        if self._finished_at is not None:
            # linger: late (transient_local) readers and reliable resends still get served
            self.done = time.monotonic() >= self._finished_at + self.linger_s
            return
        if self._start_at is None and self._matched():
            self._start_at = time.monotonic() + self._start_delay
        if self._start_at is None or time.monotonic() < self._start_at:
            return
        for _ in range(BATCH):
            item = self._next()
            if item is None:
                self._finish()
                return
            schema, channel, msg = item
            if channel.topic in self.exclude:
                self._pending = None
                continue
            t = self._time_of(channel, msg)
            if t is not None and self._t0_time is None:
                self._t0_time, self._t0_wall = t, time.monotonic()
            if self.rate > 0.0 and t is not None:
                due = self._t0_wall + (t - self._t0_time) * 1e-9 / self.rate
                if time.monotonic() < due:
                    return
            pub = self._publisher(schema, channel)
            if pub is not None:
                pub.publish(bytes(msg.data))
                self.published += 1
            self._pending = None

    def _matched(self) -> bool:
        """The /ego/odom publisher has ``wait_subscribers`` matched readers (logs while not)."""
        pubs = [pb for pb in self._pubs.values() if pb is not None and pb.topic_name == WAIT_TOPIC]
        if all(pb.get_subscription_count() >= self.wait_subscribers for pb in pubs):
            return True
        if time.monotonic() - self._waiting_since > WAIT_LOG_PERIOD_S:
            self._waiting_since = time.monotonic()
            counts = {pb.topic_name: pb.get_subscription_count() for pb in pubs}
            self.get_logger().info(f"waiting for {self.wait_subscribers} subscribers: {counts}")
        return False

    def _time_of(self, channel, msg) -> Optional[int]:
        """The message's time on the playback time line (ns), or None: publish right away.

        With ``timing:=clock`` only /clock messages carry time (their sim time); the other
        messages follow the /clock before them, as the world published them.
        """
        if self.timing == "log":
            return msg.log_time
        if channel.topic != I.TOPIC_CLOCK:
            return None
        try:
            return I.stamp_to_ns(deserialize_message(bytes(msg.data), ClockMsg).clock)
        except Exception as exc:  # a damaged /clock sample: keep playing, unpaced
            self.get_logger().warning(f"undecodable /clock message ({exc}): not used for timing",
                                      throttle_duration_sec=5.0)
            return None

    def _finish(self) -> None:
        self._finished_at = time.monotonic()
        if self.published == 0 and not self.report.complete:
            self.get_logger().error(f"nothing playable in {self.path}: {self.report.error}")
            self.exit_code = 1
        elif not self.report.complete:
            self.get_logger().warning(f"{self.path} is damaged; played the {self.published} readable "
                                      f"messages ({self.report.error})")
        else:
            self.get_logger().info(f"played {self.published} messages from {self.path}")


def main(argv=None) -> int:
    def make(args):
        if len(args) > 1:
            raise ValueError(f"usage: mcap_player [FILE.mcap] [--ros-args ...] (got {args})")
        return McapPlayer(path=args[0] if args else None)
    return run_single(make, argv)


if __name__ == "__main__":
    raise SystemExit(main())
