"""MCAP recorder: every topic of the graph, raw CDR, rosbag2-compatible (``ros2 bag`` / Foxglove).

Usage::

    mcap_recorder --ros-args -p output:=run.mcap            # or: mcap_recorder run.mcap

Topics are (re)discovered every ``discovery_period_s``; a topic is subscribed once a
publisher exists, with the QoS rosbag2 would request (reliable / transient_local only
if every publisher offers it), so latched topics such as /goal_pose are captured too.

Crash safety: messages go into chunks of about ``chunk_size`` bytes; a full chunk is
written and handed to the OS at once, and a partial chunk is written at least every
``flush_period_s``. A ``kill -9`` therefore loses at most the last chunk / flush
period; the file has no summary then, and ``mcap_io.iter_mcap`` (or any reader that
scans records) still reads it. SIGINT/SIGTERM drain pending callbacks and write the
summary: nothing received is lost.

Bag metadata: like rosbag2_storage_mcap, a metadata record named ``rosbag2`` whose key
``serialized_metadata`` holds the bag's metadata as YAML (rosbag2's BagMetadata encoding:
the body of metadata.yaml's ``rosbag2_bagfile_information``, version 9, storage
``mcap``, ``ros_distro: jazzy``). One is written at the start (so a killed recording
still names its format) and a final one with the message counts before the summary;
rosbag2 reads them in order, so the final one wins.

The map: a metadata record named ``bimacppo`` (``mcap_io.RUN_METADATA``) with ``map_id``, the
world's ``map_id`` parameter as the world holds it (a map id or a YAML path), so that
``bimacppo-sim render-bag`` draws the recording on its own road without being told. The recorder
asks the world node's parameter service (``world/get_parameters``, relative to its own namespace)
as soon as that service appears, with an asynchronous request answered through the executor:
recording never waits for it, and without a world (a recording of a player, of another source,
of a graph without world) no record is written and nothing is reported. This is ROS's own
answer to "which map does the world run on", so the recorder needs no parameter of its own that
the bringup table would have to keep equal to the world's (a recorder started by hand, beside any
world, gets it right too); the world reads ``map_id`` once at start-up, so the answer holds for
the whole run. A request the world never answers (it went away) is dropped after
``MAP_QUERY_TIMEOUT_S`` and asked again once a world serves it; a world that answers without a
string ``map_id`` (not ours) is not asked again. The first answer is the recording's map: a world
restarted on another map during one recording is not followed.

When ``map_id`` names a file the recorder can read, the record also holds that file's text
(``map_yaml``): a map file is typically local (a junction drawn for one experiment, a temporary
file), a recording is what gets copied elsewhere, and the few kilobytes keep the bag renderable
where the file does not exist or has changed since. The text is read when the world answers, from
the path as the recorder resolves it: the same file the world loaded when both run on one machine
from one working directory (the one-process graph, a launch); a path the recorder cannot read is
recorded by name only. The record is written (outside any chunk) and handed to the OS as soon as
the answer arrives, so a killed recording keeps it too.
"""
from __future__ import annotations

import importlib
import os
import threading
import time
from datetime import datetime
from typing import Dict, List

import yaml
from rcl_interfaces.msg import ParameterDescriptor, ParameterType
from rcl_interfaces.srv import GetParameters
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from bimacppo_interfaces import contract as I
from bimacppo_ros_common.params import declare
from bimacppo_ros_common.runtime import optional_path_arg, run_single

from . import mcap_io

MIN_PERIOD_S = 0.01   # shortest discovery / flush period: a timer at 0 s fires on every spin
MAP_QUERY_TIMEOUT_S = 5.0   # an unanswered request for the world's map_id is asked again after this
WORLD_MAP_PARAMETER = "map_id"

STRING_ARRAY = ParameterDescriptor(type=ParameterType.PARAMETER_STRING_ARRAY)


def import_message_type(type_name: str):
    """``pkg/msg/Type`` -> the generated Python class (LookupError if not installed)."""
    pkg, ns, name = mcap_io.split_type(type_name)
    try:
        return getattr(importlib.import_module(f"{pkg}.{ns}"), name)
    except (ImportError, AttributeError) as exc:
        raise LookupError(f"message type {type_name} is not importable here ({exc})") from None


def string_list(node, name: str) -> list:
    """A STRING_ARRAY parameter declared without default: unset means []."""
    from rclpy.exceptions import ParameterUninitializedException
    try:
        return list(node.get_parameter(name).value or [])
    except ParameterUninitializedException:
        return []


def _policy_name(p) -> str:
    return str(getattr(p, "name", p)).lower()


def _qos_record(profile) -> mcap_io.QosRecord:
    def ns(d):
        return getattr(d, "nanoseconds", None)
    return mcap_io.QosRecord(
        history=_policy_name(profile.history), depth=int(profile.depth),
        reliability=_policy_name(profile.reliability), durability=_policy_name(profile.durability),
        deadline_ns=ns(profile.deadline), lifespan_ns=ns(profile.lifespan),
        liveliness=_policy_name(profile.liveliness),
        liveliness_lease_ns=ns(profile.liveliness_lease_duration),
        avoid_ros_namespace_conventions=bool(profile.avoid_ros_namespace_conventions))


def adapted_request(records: List[mcap_io.QosRecord], depth: int) -> QoSProfile:
    """rosbag2's ``adapt_request_to_offers``: strongest policy that matches every publisher."""
    reliable = bool(records) and all(r.reliability == "reliable" for r in records)
    latched = bool(records) and all(r.durability == "transient_local" for r in records)
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth,
                      reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE)


class McapRecorder(Node):
    """Records raw CDR of every (selected) topic into one MCAP file."""

    def __init__(self, output: str | None = None, **kwargs) -> None:
        super().__init__(I.RECORDER_NODE, **kwargs)
        out = declare(self, "output", "", "MCAP file to write (never overwritten); empty: the positional "
                                         "argument, else bimacppo_<date>_<time>.mcap")
        # a period of 0 would be a timer firing on every spin (a busy loop), a negative one an RCLError
        discovery = declare(self, "discovery_period_s", 0.5, "how often new topics are looked for (wall s)",
                            lo=MIN_PERIOD_S, hi=3600.0)
        chunk = declare(self, "chunk_size", 65536, "MCAP chunk size (bytes)", lo=1, hi=2**31 - 1)
        flush = declare(self, "flush_period_s", 1.0, "how often the file is flushed (wall s)",
                        lo=MIN_PERIOD_S, hi=3600.0)
        compression = declare(self, "compression", "zstd", "chunk compression", choices=mcap_io.COMPRESSIONS)
        declare(self, "topics", Parameter.Type.STRING_ARRAY, "record only these topics (unset: every topic)")
        declare(self, "exclude", Parameter.Type.STRING_ARRAY, "never record these topics")
        # Per-topic history the recorder can fall behind by before DDS drops the oldest: a lockstep
        # loop runs hundreds of ticks per second, so 1,000 is seconds of slack for a chunk write
        # or a scheduling stall on a loaded machine.
        self.depth = declare(self, "queue_depth", 1000, "per-topic subscription depth", lo=1, hi=1_000_000)
        path = output or out or datetime.now().strftime("bimacppo_%Y%m%d_%H%M%S.mcap")
        self.path = os.path.abspath(path)
        self.topics = {t for t in string_list(self, "topics") if t}
        self.exclude = {t for t in string_list(self, "exclude") if t}
        os.makedirs(os.path.dirname(self.path) or ".", exist_ok=True)
        self._writer, self._file = mcap_io.open_writer(self.path, chunk, compression)
        self._topic_meta: Dict[str, dict] = {}
        self._time_range: List[int] = []        # first and last log time (ns)
        self._lock = threading.Lock()
        self.counts: Dict[str, int] = {}
        self._write_bag_metadata()
        self._schemas: Dict[str, int] = {}
        self._channels: Dict[str, int] = {}
        self._subs = {}
        self._type_warned = set()   # (topic, types) already warned about: once each, whenever it appears
        self._seq: Dict[int, int] = {}
        self._closed = False
        self.map_id = ""            # the world's map_id, once recorded
        self._map_client = self.create_client(GetParameters, f"{I.WORLD_NODE}/get_parameters")
        self._map_request = None    # (future, monotonic time sent) while the world is asked
        self._map_answered = False  # a world answered (with a map or without): not asked again
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(discovery, self.discover, clock=steady)
        self.create_timer(flush, self.flush, clock=steady)
        self.get_logger().info(f"recording to {self.path}")   # first: the topic lines below belong to it
        self.discover()

    # ------------------------------------------------------------------ discovery
    def _selected(self, topic: str) -> bool:
        if topic in self.exclude:
            return False
        return not self.topics or topic in self.topics

    def discover(self) -> None:
        """Subscribe to every new topic that has a publisher (called by a timer, or directly)."""
        if self._closed:
            return
        self._ask_world_map()
        for topic, types in self.get_topic_names_and_types():
            if not self._selected(topic) or (topic in self._subs and topic not in I.TOPIC_TYPES):
                continue
            # a topic of the contract is recorded with its documented type only (whichever
            # publisher appeared first), and a publisher of another type is warned about also
            # when it appears after the subscription; another topic needs a single type
            type_name = I.TOPIC_TYPES.get(topic, types[0] if len(types) == 1 else None)
            others = [t for t in types if t != type_name]
            key = (topic, tuple(sorted(types)))
            if others and key not in self._type_warned:
                self._type_warned.add(key)
                if type_name is None:
                    self.get_logger().warning(f"{topic}: several types {types}, not recorded")
                else:
                    self.get_logger().warning(f"{topic}: offered as {types}; recording the documented "
                                              f"{type_name}, not {others}")
            if topic in self._subs or type_name is None:
                continue
            if type_name not in types:
                continue                 # only other types so far: wait for the documented one
            infos = [i for i in self.get_publishers_info_by_topic(topic) if i.topic_type == type_name]
            if not infos:
                continue
            try:
                self._subscribe(topic, type_name, infos)
            except (LookupError, mcap_io.DefinitionNotFound) as exc:
                self.get_logger().warning(f"{topic}: not recorded: {exc}")
                self._subs[topic] = None

    def _subscribe(self, topic: str, type_name: str, infos) -> None:
        msg_cls = import_message_type(type_name)
        records = [_qos_record(i.qos_profile) for i in infos]
        with self._lock:
            if type_name not in self._schemas:
                text = mcap_io.full_definition(type_name)
                self._schemas[type_name] = self._writer.register_schema(
                    type_name, mcap_io.SCHEMA_ENCODING, text.encode())
            meta = {"offered_qos_profiles": mcap_io.qos_to_yaml(records)}
            h = getattr(infos[0], "topic_type_hash", None)
            if h is not None and str(h):
                meta["topic_type_hash"] = str(h)
            cid = self._writer.register_channel(topic, mcap_io.MESSAGE_ENCODING,
                                                self._schemas[type_name], meta)
            self._channels[topic] = cid
            self._topic_meta[topic] = {
                "name": topic, "type": type_name, "serialization_format": mcap_io.MESSAGE_ENCODING,
                "offered_qos_profiles": meta["offered_qos_profiles"],
                "type_description_hash": meta.get("topic_type_hash", "")}
        self._subs[topic] = self.create_subscription(
            msg_cls, topic, lambda data, c=cid, t=topic: self._on_message(c, t, data),
            adapted_request(records, self.depth), raw=True)
        self.get_logger().info(f"recording {topic} [{type_name}]")

    # ------------------------------------------------------------------ the world's map
    def _ask_world_map(self) -> None:
        """Ask the world's parameter service for its map_id, once it serves (never waits)."""
        if self._map_answered:
            return
        if self._map_request is not None:
            future, sent = self._map_request
            if time.monotonic() - sent < MAP_QUERY_TIMEOUT_S:
                return
            self._map_client.remove_pending_request(future)   # the world went away: ask the next one
            self._map_request = None
        if not self._map_client.service_is_ready():
            return
        future = self._map_client.call_async(GetParameters.Request(names=[WORLD_MAP_PARAMETER]))
        self._map_request = (future, time.monotonic())
        future.add_done_callback(self._on_world_map)

    def _on_world_map(self, future) -> None:
        if self._map_request is None or self._map_request[0] is not future:
            return                                           # a request given up on
        self._map_request = None
        self._map_answered = True
        try:
            values = future.result().values
        except Exception:   # noqa: BLE001 - a failed request: the bag just names no map
            return
        if len(values) != 1 or values[0].type != ParameterType.PARAMETER_STRING or not values[0].string_value:
            return
        self._write_map(values[0].string_value)

    def _write_map(self, map_id: str) -> None:
        record = {mcap_io.MAP_ID_KEY: map_id}
        if os.path.isfile(map_id):
            try:
                with open(map_id, encoding="utf-8") as fh:
                    record[mcap_io.MAP_YAML_KEY] = fh.read()
            except (OSError, UnicodeDecodeError):
                pass                                         # recorded by name only
        with self._lock:
            if self._closed:
                return
            self._writer.add_metadata(mcap_io.RUN_METADATA, record)
            self._file.flush()
        self.map_id = map_id
        with_text = " with its text" if mcap_io.MAP_YAML_KEY in record else ""
        self.get_logger().info(f"the world runs on map {map_id}: recorded{with_text}")

    # ------------------------------------------------------------------ writing
    def _on_message(self, channel_id: int, topic: str, data: bytes) -> None:
        t = time.time_ns()
        with self._lock:
            if self._closed:
                return
            seq = self._seq.get(channel_id, 0)
            self._seq[channel_id] = seq + 1
            self._writer.add_message(channel_id=channel_id, log_time=t, data=bytes(data),
                                     publish_time=t, sequence=seq)
            self._file.flush()  # a chunk the writer just completed goes to the OS now
            self.counts[topic] = self.counts.get(topic, 0) + 1
            if self._time_range:
                self._time_range[1] = t
            else:
                self._time_range = [t, t]

    def bag_metadata(self) -> dict:
        """rosbag2's BagMetadata (version 9) of what has been recorded so far."""
        start, end = self._time_range or [0, 0]
        duration = {"nanoseconds": int(end - start)}
        starting = {"nanoseconds_since_epoch": int(start)}
        total = sum(self.counts.values())
        name = os.path.basename(self.path)
        return {
            "version": 9, "storage_identifier": "mcap", "duration": duration, "starting_time": starting,
            "message_count": total,
            "topics_with_message_count": [{"topic_metadata": dict(m), "message_count": self.counts.get(t, 0)}
                                          for t, m in sorted(self._topic_meta.items())],
            # rosbag2's compression fields name its own file/message compression (none here);
            # the MCAP chunk compression is stated by each chunk
            "compression_format": "", "compression_mode": "",
            "relative_file_paths": [name],
            "files": [{"path": name, "starting_time": starting, "duration": duration, "message_count": total}],
            "custom_data": {},
            "ros_distro": "jazzy",
        }

    def _write_bag_metadata(self) -> None:
        text = yaml.safe_dump(self.bag_metadata(), default_flow_style=False, sort_keys=False)
        self._writer.add_metadata("rosbag2", {"serialized_metadata": text})

    def flush(self) -> None:
        """Close the open chunk (if any) and hand it to the OS: bounds what a kill can lose."""
        with self._lock:
            if not self._closed:
                self._writer.flush()

    def close(self) -> None:
        """Write the summary (indexes, statistics) and close the file; idempotent."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            self._write_bag_metadata()
            self._writer.finish()
            self._file.close()
        total = sum(self.counts.values())
        self.get_logger().info(f"wrote {total} messages on {len(self.counts)} topics to {self.path}")


def main(argv=None) -> int:
    def make(args):
        return McapRecorder(output=optional_path_arg(args, "mcap_recorder [OUTPUT.mcap] [--ros-args ...]"))
    return run_single(make, argv)


if __name__ == "__main__":
    raise SystemExit(main())
