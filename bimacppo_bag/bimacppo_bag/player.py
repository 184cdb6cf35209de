"""MCAP player: republishes a recording on its topics, so a recorded drive stands in for the world.

Usage::

    mcap_player run.mcap --ros-args -p rate:=1.0 -p topics:="['/clock','/ego/odom','/objects','/goal_pose']"
    mcap_player path/to/rosbag2_dir                       # metadata.yaml + .mcap files

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
for good (volatile QoS). Stand-in use therefore passes ``wait_subscribers:=2``.

Any ROS 2 MCAP plays, whoever wrote it:

* the path is an ``.mcap`` file or a rosbag2 directory (``metadata.yaml`` + its ``.mcap``
  files, played in the listed order as one time line; sqlite3 storage is refused);
* messages go out in log-time order, also when the writer stored them grouped by topic;
* each topic is re-offered with the QoS recorded in its channel metadata (else the
  directory's metadata.yaml); without a record, a topic of the contract gets its
  documented profile (``contract.TOPIC_QOS``: /goal_pose latched), any other topic
  reliable/volatile;
* ``timing:=clock`` on a bag without /clock messages falls back to log timing with one
  warning (a stand-in run should not die of a missing clock: its log times still pace it);
* a topic recorded with a type other than the one already on the graph (``/rosout`` as
  std_msgs/String next to every node's rcl_interfaces/Log) is skipped with a warning; a
  topic of the contract recorded with its documented type is played regardless;
* chunk CRCs are checked: a damaged chunk is skipped with a warning and playback goes on
  with the next one, so no garbled message is published (a writer that stored no CRC,
  e.g. rosbag2's default, cannot be checked);
* at the end one line per topic says how many messages were played and skipped, and why.

A truncated file is played up to its first unreadable byte and the reason is logged; a
missing file or one without any message is a one-line error, not a traceback.
"""
from __future__ import annotations

import os
import time
from typing import Dict, Optional, Tuple

from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from rosgraph_msgs.msg import Clock as ClockMsg

from bimacppo_interfaces import contract as I
from bimacppo_ros_common.params import declare
from bimacppo_ros_common.runtime import SetupException, optional_path_arg, run_single

from . import mcap_io
from .recorder import import_message_type, string_list

BATCH = 200
"""Messages published per timer callback at most, so the executor stays responsive."""

TIMINGS = ("log", "clock")
WORLD_TOPICS = (I.TOPIC_CLOCK, I.TOPIC_EGO_ODOM, I.TOPIC_OBJECTS, I.TOPIC_MARKERS, I.TOPIC_GOAL,
                I.TOPIC_RESULT)
"""What the world node publishes: the player's topics when it stands in for the world."""
WAIT_TOPIC = I.TOPIC_EGO_ODOM
WAIT_LOG_PERIOD_S = 5.0


def offered_qos(metadata: Dict[str, str], min_depth: int, topic: str = "",
                fallback_yaml: str = "") -> QoSProfile:
    """The QoS to re-offer on ``topic``.

    The recorded publishers' policies (channel metadata, else ``fallback_yaml`` from a
    rosbag2 metadata.yaml) if they agree; without any record the contract's documented
    profile of the topic (``contract.TOPIC_QOS``); else reliable/volatile. Volatile
    topics get at least ``min_depth`` so a burst at ``rate:=0`` is not dropped by the writer.
    """
    recs = mcap_io.qos_from_yaml(metadata.get("offered_qos_profiles", "")) or \
        mcap_io.qos_from_yaml(fallback_yaml)
    rel = ReliabilityPolicy.RELIABLE
    dur = DurabilityPolicy.VOLATILE
    depth = min_depth
    if recs:
        if all(r.reliability == "best_effort" for r in recs):
            rel = ReliabilityPolicy.BEST_EFFORT
        if all(r.durability == "transient_local" for r in recs):
            dur = DurabilityPolicy.TRANSIENT_LOCAL
            depth = max(1, max(r.depth for r in recs))
    elif topic in I.TOPIC_QOS:
        doc = I.TOPIC_QOS[topic]
        rel, dur = doc.reliability, doc.durability
        depth = doc.depth if dur == DurabilityPolicy.TRANSIENT_LOCAL else max(min_depth, doc.depth)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=rel, durability=dur)


class McapPlayer(Node):
    """Publishes the messages of one bag (file or rosbag2 directory) at recorded timing."""

    def __init__(self, path: Optional[str] = None, **kwargs) -> None:
        super().__init__(I.PLAYER_NODE, **kwargs)
        bag = declare(self, "path", "", "the bag: an MCAP file or a rosbag2 directory (or the positional argument)")
        self.rate = declare(self, "rate", 1.0, "playback speed (0 = as fast as possible)", lo=0.0, hi=1e6)
        self._start_delay = declare(self, "start_delay_s", 1.0, "wait before the first message, so "
                                    "subscribers match (wall s)", lo=0.0, hi=3600.0)
        declare(self, "topics", Parameter.Type.STRING_ARRAY, "play only these topics (unset: every topic)")
        declare(self, "exclude", Parameter.Type.STRING_ARRAY, "never play these topics")
        self.depth = declare(self, "queue_depth", 100, "publisher queue depth", lo=1, hi=1_000_000)
        period = declare(self, "period_s", 0.002, "playback timer period (wall s)", lo=0.0001, hi=1.0)
        self.linger_s = declare(self, "linger_s", 1.0, "keep publishers up this long after the last message "
                                "(wall s)", lo=0.0, hi=3600.0)
        self.timing = declare(self, "timing", "log", "pace by the recorded log times, or by /clock", choices=TIMINGS)
        as_world = declare(self, "as_world", False, "play only the world's topics: the bag stands in for the world")
        self.wait_subscribers = declare(self, "wait_subscribers", 0, "start once this many subscribers match "
                                        f"{WAIT_TOPIC} (0: after start_delay_s)", lo=0, hi=1000)
        self.path = path or bag
        if not self.path:
            raise ValueError("mcap_player: no file given (positional argument or -p path:=FILE.mcap)")
        if not os.path.exists(self.path):
            raise FileNotFoundError(f"mcap_player: no such file: {self.path}")
        try:
            self.files, self._bag_qos = mcap_io.bag_files(self.path)
        except mcap_io.BagError as exc:
            raise ValueError(f"mcap_player: {exc}") from None
        self.topics = set(string_list(self, "topics"))
        if as_world:
            if self.topics:
                raise ValueError("mcap_player: give either topics or as_world:=true, not both")
            self.topics = set(WORLD_TOPICS)
        if self.timing == "clock" and self.topics and I.TOPIC_CLOCK not in self.topics:
            raise ValueError(f"mcap_player: timing:=clock needs {I.TOPIC_CLOCK} among the played topics")
        self.exclude = set(string_list(self, "exclude"))
        # a first pass finds every topic, so all publishers exist (and get matched during
        # start_delay_s) before the first message goes out: nothing early is lost
        self._pubs: Dict[str, Tuple[str, object]] = {}     # topic -> (type, publisher or None)
        self._why: Dict[str, str] = {}                     # topic -> why it is not played
        self.played: Dict[str, int] = {}
        self.skipped: Dict[str, int] = {}
        scan = mcap_io.ReadReport()
        for schema, channel, _ in self._iter(scan):
            if channel.topic not in self._pubs and channel.topic not in self.exclude:
                self._publisher(schema, channel)
        if self.timing == "clock" and not scan.topics.get(I.TOPIC_CLOCK):
            self.get_logger().warning(f"timing:=clock, but {self.path} has no {I.TOPIC_CLOCK} messages: "
                                      "paced by the recorded log times instead")
            self.timing = "log"
        self.report = mcap_io.ReadReport()
        self._it = self._iter(self.report)
        self._finished_at: Optional[float] = None
        self._pending = None
        self._t0_time: Optional[int] = None
        self._t0_wall: Optional[float] = None
        self._start_at: Optional[float] = None if self.wait_subscribers else time.monotonic() + self._start_delay
        self._waiting_since = time.monotonic()
        if self.wait_subscribers and self._wait_pub() is None:
            raise ValueError(f"mcap_player: wait_subscribers needs {WAIT_TOPIC} among the played topics")
        self.published = 0
        self.done = False
        self.exit_code = 0
        self._timer = self.create_timer(period, self._tick,
                                        clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _iter(self, report: mcap_io.ReadReport):
        """Every message of every file of the bag, file after file (one time line)."""
        for f in self.files:
            yield from mcap_io.iter_mcap(f, report, topics=self.topics or None)

    def _clashing_types(self, topic: str, type_name: str) -> list:
        """Other types this topic already has on the graph (own publishers included)."""
        for name, types in self.get_topic_names_and_types():
            if name == topic:
                return [t for t in types if t != type_name]
        return []

    def _skip(self, topic: str, type_name: str, why: str):
        self.get_logger().warning(f"{topic}: not played ({why})")
        self._pubs[topic] = (type_name, None)
        self._why[topic] = why
        return None

    def _publisher(self, schema, channel):
        topic = channel.topic
        type_name = schema.name if schema is not None else ""
        if topic in self._pubs:
            known, pub = self._pubs[topic]
            if known != type_name:   # another file of the bag with another type on this topic
                self._why.setdefault(topic, f"also recorded as {type_name}, played as {known}")
                return None
            return pub
        if schema is None or channel.message_encoding != mcap_io.MESSAGE_ENCODING:
            return self._skip(topic, type_name, f"encoding {channel.message_encoding!r} is not ROS 2 CDR")
        try:
            cls = import_message_type(type_name)
        except (LookupError, mcap_io.DefinitionNotFound) as exc:
            return self._skip(topic, type_name, str(exc))
        others = self._clashing_types(topic, type_name)
        if others and I.TOPIC_TYPES.get(topic) != type_name:
            return self._skip(topic, type_name, f"recorded as {type_name}, but the graph has it as {others}")
        qos = offered_qos(channel.metadata, self.depth, topic, self._bag_qos.get(topic, ""))
        try:
            pub = self.create_publisher(cls, topic, qos)
        except SetupException as exc:   # e.g. rcl: this process already has the topic with another type
            return self._skip(topic, type_name, f"cannot publish it as {type_name}: {str(exc).splitlines()[0]}")
        self._pubs[topic] = (type_name, pub)
        return pub

    def _wait_pub(self):
        return self._pubs.get(WAIT_TOPIC, (None, None))[1]

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
                self.played[channel.topic] = self.played.get(channel.topic, 0) + 1
            else:
                self.skipped[channel.topic] = self.skipped.get(channel.topic, 0) + 1
            self._pending = None

    def _matched(self) -> bool:
        """The /ego/odom publisher has ``wait_subscribers`` matched readers (logs while not)."""
        pb = self._wait_pub()
        if pb is None or pb.get_subscription_count() >= self.wait_subscribers:
            return True
        if time.monotonic() - self._waiting_since > WAIT_LOG_PERIOD_S:
            self._waiting_since = time.monotonic()
            counts = {pb.topic_name: pb.get_subscription_count()}
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

    def summary_lines(self) -> list:
        """One line per topic: messages played, skipped and why (damaged chunks included)."""
        lines = []
        for topic in sorted(set(self.played) | set(self.skipped) | set(self.report.lost)):
            why = []
            if self.skipped.get(topic):
                why.append(f"{self.skipped[topic]} {self._why.get(topic, 'not played')}")
            if self.report.lost.get(topic):
                why.append(f"{self.report.lost[topic]} in damaged chunks")
            n_skip = self.skipped.get(topic, 0) + self.report.lost.get(topic, 0)
            lines.append(f"{topic}: played {self.played.get(topic, 0)}, skipped {n_skip}"
                         + (f" ({'; '.join(why)})" if why else ""))
        if self.report.lost_unknown:
            lines.append(f"{self.report.lost_unknown} damaged chunks or messages of unknown topic skipped")
        return lines

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
        for line in self.summary_lines():
            self.get_logger().info(f"summary {line}")


def main(argv=None) -> int:
    def make(args):
        return McapPlayer(path=optional_path_arg(args, "mcap_player [FILE.mcap | ROSBAG2_DIR] [--ros-args ...]"))
    return run_single(make, argv)


if __name__ == "__main__":
    raise SystemExit(main())
