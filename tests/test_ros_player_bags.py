"""The MCAP player on bags written by other libraries (never by our recorder).

Bags are made with ``mcap_ros2``'s writer (its own CDR encoder, no QoS metadata, free
message order) and ``rosbags`` (rosbag2 directories with metadata.yaml); message
definitions come from rosbags' typestore where rosbags is installed, so nothing here
depends on our writer side (without rosbags the directory test is skipped).
Each test plays one such bag into this process over DDS and checks what arrives.
"""
import math
import os
import shutil
import signal
import subprocess
import sys
import time

import pytest
import yaml

rclpy = pytest.importorskip("rclpy")
pytestmark = pytest.mark.ros

from mcap_ros2.writer import Writer as Ros2Writer  # noqa: E402
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy  # noqa: E402
from rclpy.serialization import serialize_message  # noqa: E402

from bimacppo_interfaces import contract as I  # noqa: E402
from bimacppo_bag import mcap_io  # noqa: E402

os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
PROC_TIMEOUT = 30
T0 = 1_700_000_000_000_000_000       # log times: an ordinary wall-clock epoch (ns)
ODOM = "nav_msgs/msg/Odometry"


@pytest.fixture(scope="module")
def node():
    rclpy.init()
    n = rclpy.create_node("test_player_bags")
    yield n
    n.destroy_node()
    rclpy.try_shutdown()


@pytest.fixture(scope="module")
def typestore():
    """rosbags' Jazzy typestore, or None where rosbags is not installed."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        return None
    return get_typestore(Stores.ROS2_JAZZY)


def _msgdef(typestore, type_name):
    """The .msg text of a type from rosbags' typestore (independent of our writer side), else ours."""
    if typestore is None:
        return mcap_io.full_definition(type_name)
    return typestore.generate_msgdef(type_name, ros_version=2)[0]


def _spin(node, seconds):
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.01)


def _play(node, bag, *params, until=None):
    """Run the player on ``bag`` to its end while spinning ``node``; returns (rc, output)."""
    args = [sys.executable, "-m", "bimacppo_bag.player", str(bag), "--ros-args",
            "-p", "start_delay_s:=0.3", "-p", "linger_s:=0.5"]
    for p in params:
        args += ["-p", p]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t_end = time.monotonic() + PROC_TIMEOUT
    while proc.poll() is None and time.monotonic() < t_end:
        _spin(node, 0.05)
        if until is not None:
            until(proc)
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=PROC_TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f"player did not stop: {out}")
    _spin(node, 0.2)
    return proc.returncode, out


def _odom(k):
    """Odometry number k: x = k, y = 2k, stamped k * 0.1 s (what every test checks against)."""
    return {"header": {"stamp": {"sec": k // 10, "nanosec": (k % 10) * 100_000_000}, "frame_id": "map"},
            "child_frame_id": "base_link",
            "pose": {"pose": {"position": {"x": float(k), "y": 2.0 * k}, "orientation": {"w": 1.0}}}}


def _ros2_bag(path, typestore, messages, chunk_size=1024 * 1024):
    """An MCAP written by mcap_ros2: ``messages`` = [(topic, type, dict, log_time)] in file order."""
    schemas = {}
    with open(path, "wb") as f:
        w = Ros2Writer(f, chunk_size=chunk_size)
        for topic, type_name, msg, t in messages:
            if type_name not in schemas:
                schemas[type_name] = w.register_msgdef(type_name, _msgdef(typestore, type_name))
            w.write_message(topic, schemas[type_name], msg, log_time=t, publish_time=t)
        w.finish()
    return path


READER_QOS = QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                        durability=DurabilityPolicy.VOLATILE)
"""Deep enough for a whole bag played at ``rate:=0`` (keep_last 10 would drop part of the burst)."""


def _odom_sub(node, got, topic=I.TOPIC_EGO_ODOM):
    return node.create_subscription(I.Odometry, topic, got.append, READER_QOS)


def _xy(msgs):
    return [(m.pose.pose.position.x, m.pose.pose.position.y) for m in msgs]


def _summary(out, topic):
    return [ln for ln in out.splitlines() if f"summary {topic}:" in ln]


def test_bag_without_qos_metadata_reoffers_documented_profiles(node, tmp_path, typestore):
    """No offered_qos_profiles: /goal_pose is re-offered latched, so a late reader gets the goal."""
    goal = {"header": {"stamp": {"sec": 0, "nanosec": 100_000_000}, "frame_id": "map"},
            "pose": {"position": {"x": 10.0, "y": -3.5}, "orientation": {"w": 1.0}}}
    msgs = [(I.TOPIC_GOAL, "geometry_msgs/msg/PoseStamped", goal, T0)]
    msgs += [(I.TOPIC_EGO_ODOM, ODOM, _odom(k), T0 + (k + 1) * 1_000_000) for k in range(20)]
    bag = _ros2_bag(tmp_path / "noqos.mcap", typestore, msgs)
    from mcap.reader import make_reader
    with open(bag, "rb") as f:
        assert all("offered_qos_profiles" not in c.metadata
                   for c in make_reader(f).get_summary().channels.values())

    odoms, goals, qos_seen = [], [], {}
    sub = _odom_sub(node, odoms)
    late = []

    def join_late(proc):
        # after the goal and every odometry went out, read the publishers' QoS and only then
        # subscribe to /goal_pose: a volatile goal would be gone by now
        if len(odoms) == 20 and not late:
            for topic in (I.TOPIC_GOAL, I.TOPIC_EGO_ODOM):
                infos = node.get_publishers_info_by_topic(topic)
                qos_seen[topic] = [i.qos_profile.durability for i in infos]
            late.append(node.create_subscription(I.PoseStamped, I.TOPIC_GOAL, goals.append, I.LATCHED_QOS))

    rc, out = _play(node, bag, "rate:=0.0", "wait_subscribers:=1", "linger_s:=5.0", until=join_late)
    for s in [sub] + late:
        node.destroy_subscription(s)
    assert rc == 0 and "Traceback" not in out, out
    assert _xy(odoms) == [(float(k), 2.0 * k) for k in range(20)], out
    assert qos_seen[I.TOPIC_GOAL] == [DurabilityPolicy.TRANSIENT_LOCAL], (qos_seen, out)
    assert qos_seen[I.TOPIC_EGO_ODOM] == [DurabilityPolicy.VOLATILE], (qos_seen, out)
    assert len(goals) == 1 and goals[0].pose.position.x == 10.0, out


def test_bag_grouped_by_topic_plays_in_log_time_order(node, tmp_path, typestore):
    """File order = topic by topic, second half of the drive first; playback = log-time order."""
    ref = [(I.TOPIC_REFERENCE, ODOM, _odom(k), T0 + 2 * k * 1_000_000 + 1) for k in range(30)]
    odom = [(I.TOPIC_EGO_ODOM, ODOM, _odom(k), T0 + 2 * k * 1_000_000) for k in range(30)]
    # small chunks: the reordering must work across chunks that overlap in time
    bag = _ros2_bag(tmp_path / "grouped.mcap", typestore, ref + odom[15:] + odom[:15], chunk_size=800)
    report = mcap_io.ReadReport()
    order = [(ch.topic, m.log_time) for _, ch, m in mcap_io.iter_mcap(bag, report)]
    assert report.complete, report.error
    assert [t for _, t in order] == sorted(t for *_, t in ref + odom)
    assert order[:2] == [(I.TOPIC_EGO_ODOM, T0), (I.TOPIC_REFERENCE, T0 + 1)]

    got = []
    sub = _odom_sub(node, got)
    rc, out = _play(node, bag, "rate:=0.0", "wait_subscribers:=1")
    node.destroy_subscription(sub)
    assert rc == 0 and "Traceback" not in out, out
    assert _xy(got) == [(float(k), 2.0 * k) for k in range(30)], out


def test_timing_clock_without_clock_falls_back_to_log_timing(node, tmp_path, typestore):
    bag = _ros2_bag(tmp_path / "noclock.mcap", typestore,
                    [(I.TOPIC_EGO_ODOM, ODOM, _odom(k), T0 + k * 1_000_000) for k in range(10)])
    got = []
    sub = _odom_sub(node, got)
    rc, out = _play(node, bag, "timing:=clock", "rate:=1.0", "wait_subscribers:=1")
    node.destroy_subscription(sub)
    assert rc == 0 and "Traceback" not in out, out
    warnings = [ln for ln in out.splitlines() if "timing:=clock" in ln]
    assert len(warnings) == 1 and "WARN" in warnings[0] and "log times" in warnings[0], out
    assert _xy(got) == [(float(k), 2.0 * k) for k in range(10)], out


def test_topic_with_clashing_type_is_skipped(node, tmp_path, typestore):
    """/rosout recorded as std_msgs/String: every node has it as rcl_interfaces/Log."""
    msgs = []
    for k in range(6):
        msgs.append((I.TOPIC_EGO_ODOM, ODOM, _odom(k), T0 + 2 * k))
        if k < 3:
            msgs.append(("/rosout", "std_msgs/msg/String", {"data": f"not a log {k}"}, T0 + 2 * k + 1))
    bag = _ros2_bag(tmp_path / "clash.mcap", typestore, msgs)
    got, rosout_types = [], set()
    sub = _odom_sub(node, got)

    def watch(proc):   # what /rosout is offered as while the player runs
        rosout_types.update(*(types for name, types in node.get_topic_names_and_types() if name == "/rosout"))

    rc, out = _play(node, bag, "rate:=0.0", "wait_subscribers:=1", until=watch)
    node.destroy_subscription(sub)
    assert rc == 0 and "Traceback" not in out, out
    assert rosout_types == {"rcl_interfaces/msg/Log"}, rosout_types
    assert any("/rosout: not played" in ln and "WARN" in ln for ln in out.splitlines()), out
    assert _xy(got) == [(float(k), 2.0 * k) for k in range(6)], out
    assert len(_summary(out, "/rosout")) == 1 and "played 0, skipped 3" in _summary(out, "/rosout")[0], out
    assert "played 6, skipped 0" in _summary(out, I.TOPIC_EGO_ODOM)[0], out


def _rosbags_dir(path, typestore, ks, storage="mcap"):
    if typestore is None:
        pytest.skip("rosbags is not installed")
    from rosbags.rosbag2 import StoragePlugin, Writer
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conn = w.add_connection(I.TOPIC_EGO_ODOM, ODOM, typestore=typestore)
        for k in ks:
            m = I.state_to_odometry([float(k), 2.0 * k, 0.0, 1.0], k + 1)
            w.write(conn, T0 + k * 1_000_000, serialize_message(m))
    return path


def test_rosbag2_directory_plays_its_files_in_order(node, tmp_path, typestore):
    first = _rosbags_dir(tmp_path / "first", typestore, range(0, 12))
    second = _rosbags_dir(tmp_path / "second", typestore, range(12, 25))
    # one bag of two files, listed in play order (which is not their alphabetical order)
    meta_path = first / "metadata.yaml"
    meta = yaml.safe_load(meta_path.read_text())
    info = meta["rosbag2_bagfile_information"]
    assert info["storage_identifier"] == "mcap"
    (f1,), (f2,) = info["relative_file_paths"], yaml.safe_load(
        (second / "metadata.yaml").read_text())["rosbag2_bagfile_information"]["relative_file_paths"]
    shutil.move(first / f1, first / "b_part0.mcap")
    shutil.move(second / f2, first / "a_part1.mcap")
    info["relative_file_paths"] = ["b_part0.mcap", "a_part1.mcap"]
    info["files"] = [dict(info["files"][0], path="b_part0.mcap"), dict(info["files"][0], path="a_part1.mcap")]
    meta_path.write_text(yaml.safe_dump(meta))

    got = []
    sub = _odom_sub(node, got)
    rc, out = _play(node, first, "rate:=0.0", "wait_subscribers:=1")
    node.destroy_subscription(sub)
    assert rc == 0 and "Traceback" not in out, out
    assert _xy(got) == [(float(k), 2.0 * k) for k in range(25)], out

    # a sqlite3 bag cannot be read here: one error line, exit 2
    lite = _rosbags_dir(tmp_path / "lite", typestore, range(3), storage="sqlite3")
    rc, out = _play(node, lite)
    assert rc == 2 and "Traceback" not in out and "'sqlite3'" in out, out


def _damage_middle_chunk(src, dst):
    """Flip bytes inside the compressed records of a chunk in the middle; returns its index."""
    from mcap.reader import make_reader
    data = bytearray(src.read_bytes())
    with open(src, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    ci = chunks[len(chunks) // 2]
    assert ci.compression == "zstd"
    # chunk record: opcode, length, start, end, uncompressed size, crc, compression, records
    records_at = ci.chunk_start_offset + 9 + 8 + 8 + 8 + 4 + 4 + len(ci.compression) + 8
    for i in range(ci.compressed_size // 3, ci.compressed_size // 3 + 6):
        data[records_at + i] ^= 0x5A
    dst.write_bytes(bytes(data))
    return ci


def test_damaged_chunk_is_skipped_and_nothing_garbled_is_published(node, tmp_path, typestore):
    n = 80
    src = _ros2_bag(tmp_path / "src.mcap", typestore,
                    [(I.TOPIC_EGO_ODOM, ODOM, _odom(k), T0 + k * 1_000_000) for k in range(n)],
                    chunk_size=1500)
    bad = tmp_path / "bad.mcap"
    ci = _damage_middle_chunk(src, bad)
    report = mcap_io.ReadReport()
    xs = [m.log_time for _, _, m in mcap_io.iter_mcap(bad, report)]
    lost = report.lost.get(I.TOPIC_EGO_ODOM, 0)
    assert report.chunks_skipped == 1 and not report.complete, report
    assert 0 < lost < n and len(xs) == n - lost, report
    assert all(not (ci.message_start_time <= t <= ci.message_end_time) for t in xs)
    # without its summary (a killed writer): the record-by-record scan skips it and goes on
    data = bad.read_bytes()
    # footer = opcode, length, summary_start, summary_offset_start, crc; then the magic (8 bytes)
    summary_start = int.from_bytes(data[-37 + 9:-37 + 17], "little")
    assert 0 < summary_start < len(data)
    nosum = tmp_path / "nosummary.mcap"
    nosum.write_bytes(data[:summary_start])
    r2 = mcap_io.ReadReport()
    assert [m.log_time for _, _, m in mcap_io.iter_mcap(nosum, r2)] == xs
    assert r2.chunks_skipped == 1 and r2.lost == report.lost, r2

    got = []
    sub = _odom_sub(node, got)
    rc, out = _play(node, bad, "rate:=0.0", "wait_subscribers:=1")
    node.destroy_subscription(sub)
    assert rc == 0 and "Traceback" not in out and "damaged" in out, out
    plausible = {(float(k), 2.0 * k) for k in range(n)}
    assert all(math.isfinite(x) and math.isfinite(y) for x, y in _xy(got))
    assert set(_xy(got)) <= plausible and len(got) == n - lost, out
    line = _summary(out, I.TOPIC_EGO_ODOM)
    assert len(line) == 1 and f"played {n - lost}, skipped {lost}" in line[0] and "damaged" in line[0], out


def test_recorder_writes_rosbag2_serialized_metadata(node, tmp_path):
    """The recorder's ``rosbag2`` metadata record: rosbag2's BagMetadata YAML, readable by mcap."""
    path = tmp_path / "rec.mcap"
    odom = node.create_publisher(I.Odometry, I.TOPIC_EGO_ODOM, I.STATE_QOS)
    before = {bytes(i.endpoint_gid) for i in node.get_subscriptions_info_by_topic(I.TOPIC_EGO_ODOM)}
    rec = subprocess.Popen([sys.executable, "-m", "bimacppo_bag.recorder", str(path), "--ros-args",
                            "-p", "discovery_period_s:=0.1", "-p", f"topics:=['{I.TOPIC_EGO_ODOM}']"],
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    t_end = time.monotonic() + PROC_TIMEOUT
    while not ({bytes(i.endpoint_gid) for i in node.get_subscriptions_info_by_topic(I.TOPIC_EGO_ODOM)}
               - before) and time.monotonic() < t_end:
        _spin(node, 0.05)
    _spin(node, 0.3)
    for k in range(25):
        odom.publish(I.state_to_odometry([float(k), 0.0, 0.0, 1.0], k + 1))
        _spin(node, 0.005)
    _spin(node, 0.5)
    rec.send_signal(signal.SIGTERM)
    out, _ = rec.communicate(timeout=PROC_TIMEOUT)
    node.destroy_publisher(odom)
    assert rec.returncode == 0, out

    from mcap.reader import make_reader
    with open(path, "rb") as f:
        reader = make_reader(f)
        records = [m for m in reader.iter_metadata() if m.name == "rosbag2"]
        log_times = [msg.log_time for _, _, msg in reader.iter_messages()]
    assert records and all("serialized_metadata" in m.metadata for m in records)
    final = yaml.safe_load(records[-1].metadata["serialized_metadata"])
    assert final["version"] == 9 and final["storage_identifier"] == "mcap"
    assert final["ros_distro"] == "jazzy" and final["relative_file_paths"] == ["rec.mcap"]
    # the bag's own span, as rosbag2 computes it: from the first to the last message's log time
    assert final["message_count"] == 25 == len(log_times)
    assert final["starting_time"]["nanoseconds_since_epoch"] == min(log_times)
    assert final["duration"]["nanoseconds"] == max(log_times) - min(log_times)
    (topic,) = final["topics_with_message_count"]
    assert topic["message_count"] == 25 and topic["topic_metadata"]["name"] == I.TOPIC_EGO_ODOM
    assert topic["topic_metadata"]["type"] == ODOM
    qos = mcap_io.qos_from_yaml(topic["topic_metadata"]["offered_qos_profiles"])
    assert qos and qos[0].reliability == "reliable"
    # and our reader still reads the file completely
    report = mcap_io.ReadReport()
    assert sum(1 for _ in mcap_io.iter_mcap(path, report)) == 25 and report.complete, report.error
