"""MCAP recorder and player over real DDS (separate processes, this test's ROS domain).

Checks: clean stop writes a complete, indexed file that an independent reader
(mcap_ros2) decodes message by message; a ``kill -9`` leaves a readable file missing
only its tail; the player republishes byte-identical messages and survives damaged files;
a recording of a world node names the world's map, and render-bag draws it there.
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

from bimacppo_interfaces import contract as I  # noqa: E402
from bimacppo_bag import mcap_io  # noqa: E402

os.environ.setdefault("AMENT_PREFIX_PATH", sys.prefix)
PROC_TIMEOUT = 20


@pytest.fixture(scope="module")
def node():
    rclpy.init()
    n = rclpy.create_node("test_mcap_io")
    yield n
    n.destroy_node()
    rclpy.try_shutdown()


def _spin(node, seconds):
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        rclpy.spin_once(node, timeout_sec=0.01)


def _start(module, *args, stdout=subprocess.PIPE):
    return subprocess.Popen([sys.executable, "-m", module, *args],
                            stdout=stdout, stderr=subprocess.STDOUT, text=True)


def _stop(proc, sig=signal.SIGINT):
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, _ = proc.communicate(timeout=PROC_TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f"process did not stop: {out}")
    return proc.returncode, out


def _sub_gids(node, topic):
    return {bytes(i.endpoint_gid) for i in node.get_subscriptions_info_by_topic(topic)}


def _wait_new_subscriber(node, topic, before, timeout=10.0):
    """Wait for a subscription that was not there before (a killed process leaves ghosts)."""
    t_end = time.monotonic() + timeout
    while not (_sub_gids(node, topic) - before):
        if time.monotonic() > t_end:
            pytest.fail(f"no new subscriber on {topic} after {timeout}s")
        _spin(node, 0.05)


def _record(node, path, n_msgs, extra=()):
    """Recorder process + publishers in this process; returns the recorder (still running)."""
    odom = node.create_publisher(I.Odometry, I.TOPIC_EGO_ODOM, I.STATE_QOS)
    goal = node.create_publisher(I.PoseStamped, I.TOPIC_GOAL, I.LATCHED_QOS)
    goal.publish(I.goal_to_pose([10.0, -3.5, 1.0], 7))  # before the recorder exists: latched
    before = _sub_gids(node, I.TOPIC_EGO_ODOM)
    rec = _start("bimacppo_bag.recorder", str(path), "--ros-args", "-p", "discovery_period_s:=0.1",
                 *extra)
    _wait_new_subscriber(node, I.TOPIC_EGO_ODOM, before)
    # the graph shows the subscriber before DDS has matched it to this publisher: wait for
    # the publisher's own count, or the first messages go to nobody
    t_end = time.monotonic() + PROC_TIMEOUT
    while odom.get_subscription_count() < 1 and time.monotonic() < t_end:
        _spin(node, 0.01)
    _spin(node, 0.5)  # and let the match settle on both sides (shared-memory transport set-up)
    for k in range(n_msgs):
        odom.publish(I.state_to_odometry([float(k), 1.0, 2.0, 0.1], k + 1))
        _spin(node, 0.002)
    return rec, odom, goal


def test_recorder_clean_stop_writes_complete_indexed_file(node, tmp_path):
    path = tmp_path / "run.mcap"
    rec, odom, goal = _record(node, path, 150)
    _spin(node, 0.5)
    rc, out = _stop(rec, signal.SIGTERM)
    node.destroy_publisher(odom)
    node.destroy_publisher(goal)
    assert rc == 0, out
    assert "Traceback" not in out
    report = mcap_io.ReadReport()
    odoms = [m for _, ch, m in mcap_io.iter_mcap(path, report) if ch.topic == I.TOPIC_EGO_ODOM]
    assert report.complete, report.error
    assert len(odoms) == 150
    # no world answered: no map record, and nothing said about it
    assert mcap_io.RUN_METADATA not in report.metadata and "the world runs on map" not in out, out
    # independent reader: summary present, ros2 profile, every message decodes to what was sent
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count >= 151
        schemas = {s.name: s for s in summary.schemas.values()}
        assert schemas["nav_msgs/msg/Odometry"].encoding == "ros2msg"
        chans = {c.topic: c for c in summary.channels.values()}
        assert chans[I.TOPIC_GOAL].message_encoding == "cdr"
        qos = mcap_io.qos_from_yaml(chans[I.TOPIC_GOAL].metadata["offered_qos_profiles"])
        assert qos and qos[0].durability == "transient_local"
        xs, goals = [], []
        for _, ch, _, msg in reader.iter_decoded_messages(topics=[I.TOPIC_EGO_ODOM, I.TOPIC_GOAL]):
            if ch.topic == I.TOPIC_EGO_ODOM:
                xs.append(msg.pose.pose.position.x)
            else:
                goals.append((msg.pose.position.x, msg.pose.position.y))
    assert xs == [float(k) for k in range(150)]
    assert goals == [(10.0, -3.5)]  # the latched goal, published before recording started


def test_a_recorder_stopped_right_after_a_burst_writes_every_message(node, tmp_path):
    """1,500 messages published at once, acknowledged by the recorder's reader (so DDS has
    delivered every one), and SIGINT straight after: the recorder's executor is usually still
    working through them when the stop comes, and its drain must write all of them (they fit the
    subscription depth, queue_depth)."""
    from rclpy.duration import Duration
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from std_msgs.msg import Int32

    n = 1500
    path = tmp_path / "burst.mcap"
    pub = node.create_publisher(Int32, "/burst", QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=n,
                                                            reliability=ReliabilityPolicy.RELIABLE))
    before = _sub_gids(node, "/burst")
    rec = _start("bimacppo_bag.recorder", str(path), "--ros-args", "-p", "discovery_period_s:=0.1",
                 "-p", "queue_depth:=2000")
    _wait_new_subscriber(node, "/burst", before)
    t_end = time.monotonic() + PROC_TIMEOUT
    while pub.get_subscription_count() < 1 and time.monotonic() < t_end:
        _spin(node, 0.01)
    _spin(node, 0.5)   # the match settles on both sides
    for k in range(n):
        pub.publish(Int32(data=k))
    assert pub.wait_for_all_acked(Duration(seconds=PROC_TIMEOUT))
    rc, out = _stop(rec)
    node.destroy_publisher(pub)
    assert rc == 0, out
    report = mcap_io.ReadReport()
    from mcap_ros2.decoder import DecoderFactory
    dec = DecoderFactory()
    got = [dec.decoder_for("cdr", sch)(m.data).data for sch, _, m in mcap_io.iter_mcap(path, report, topics=["/burst"])]
    assert report.complete, report.error
    assert got == list(range(n)), (len(got), out[-2000:])


def test_player_republishes_recorded_bytes_and_survives_damage(node, tmp_path):
    path = tmp_path / "src.mcap"
    rec, odom, goal = _record(node, path, 80)
    _spin(node, 0.5)
    assert _stop(rec)[0] == 0
    node.destroy_publisher(odom)
    node.destroy_publisher(goal)
    recorded = [bytes(m.data) for _, ch, m in mcap_io.iter_mcap(path) if ch.topic == I.TOPIC_EGO_ODOM]
    assert len(recorded) == 80

    got = []
    sub = node.create_subscription(I.Odometry, I.TOPIC_EGO_ODOM, lambda b: got.append(bytes(b)),
                                   I.STATE_QOS, raw=True)
    latched = []
    gsub = node.create_subscription(I.PoseStamped, I.TOPIC_GOAL, latched.append, I.LATCHED_QOS)
    # wait_subscribers: start only once this node's reader is matched (a loaded machine can
    # take longer than any fixed delay, and volatile samples sent before the match are lost)
    play = _start("bimacppo_bag.player", str(path), "--ros-args", "-p", "rate:=4.0",
                  "-p", "wait_subscribers:=1", "-p", "start_delay_s:=0.3")
    t_end = time.monotonic() + PROC_TIMEOUT
    while play.poll() is None and time.monotonic() < t_end:
        _spin(node, 0.05)
    _spin(node, 0.3)
    rc, out = _stop(play)
    assert rc == 0, out
    assert got == recorded
    assert len(latched) == 1 and np.isclose(latched[0].pose.position.x, 10.0)

    # truncated file: plays the readable part, exits 0, says so; garbage: one-line error, rc 1
    data = path.read_bytes()
    trunc = tmp_path / "trunc.mcap"
    trunc.write_bytes(data[: len(data) * 2 // 3])
    got.clear()
    play = _start("bimacppo_bag.player", str(trunc), "--ros-args", "-p", "rate:=0.0",
                  "-p", "start_delay_s:=0.5")
    t_end = time.monotonic() + PROC_TIMEOUT
    while play.poll() is None and time.monotonic() < t_end:
        _spin(node, 0.05)
    rc, out = _stop(play)
    assert rc == 0 and "Traceback" not in out and "damaged" in out, out
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + os.urandom(2000))
    play = _start("bimacppo_bag.player", str(junk), "--ros-args", "-p", "start_delay_s:=0.0")
    out, _ = play.communicate(timeout=PROC_TIMEOUT)
    assert play.returncode == 1 and "Traceback" not in out and "nothing playable" in out, out
    missing = _start("bimacppo_bag.player", str(tmp_path / "nope.mcap"))
    out, _ = missing.communicate(timeout=PROC_TIMEOUT)
    assert missing.returncode == 2 and "no such file" in out and "Traceback" not in out, out
    node.destroy_subscription(sub)
    node.destroy_subscription(gsub)


def test_topic_offered_with_two_types_records_the_documented_one(node, tmp_path):
    """A second publisher of another type on a contract topic must not cost the recording."""
    path = tmp_path / "two_types.mcap"
    # another process (one DDS participant cannot offer one topic with two types) keeps a
    # std_msgs/String publisher on the command topic
    foreign = subprocess.Popen([sys.executable, "-c", (
        "import rclpy, time\nfrom std_msgs.msg import String\nrclpy.init()\nn = rclpy.create_node('foreign')\n"
        f"p = n.create_publisher(String, {I.TOPIC_COMMAND!r}, 10)\nt = time.monotonic() + 60\n"
        "while time.monotonic() < t:\n    p.publish(String(data='not a command'))\n    time.sleep(0.02)\n")])
    t_end = time.monotonic() + PROC_TIMEOUT
    while not node.get_publishers_info_by_topic(I.TOPIC_COMMAND) and time.monotonic() < t_end:
        _spin(node, 0.05)
    cmd = node.create_publisher(I.JointTrajectory, I.TOPIC_COMMAND, I.STATE_QOS)
    before = _sub_gids(node, I.TOPIC_COMMAND)
    # the recorder's log goes to a file, read while it runs: its own discovery of the foreign
    # participant may lag this node's by seconds on a loaded machine, so the test waits for the
    # warning (bounded) instead of assuming it came within a fixed time
    log_path = tmp_path / "recorder.log"
    warning = "recording the documented trajectory_msgs/msg/JointTrajectory"
    with open(log_path, "w") as log:
        rec = _start("bimacppo_bag.recorder", str(path), "--ros-args", "-p", "discovery_period_s:=0.1",
                     "-p", f"topics:=['{I.TOPIC_COMMAND}']", stdout=log)
    _wait_new_subscriber(node, I.TOPIC_COMMAND, before)
    t_end = time.monotonic() + PROC_TIMEOUT
    while warning not in log_path.read_text() and rec.poll() is None and time.monotonic() < t_end:
        _spin(node, 0.05)
    for k in range(20):
        cmd.publish(I.command_to_trajectory([0.5, 0.01 * k], k + 1))
        _spin(node, 0.01)
    _spin(node, 0.5)
    rc, _ = _stop(rec, signal.SIGTERM)
    out = log_path.read_text()
    foreign.kill()
    foreign.wait()
    node.destroy_publisher(cmd)
    assert rc == 0 and "Traceback" not in out, out
    assert warning in out, out
    got = [(sch.name, ch.topic) for sch, ch, _ in mcap_io.iter_mcap(path, mcap_io.ReadReport())]
    assert len(got) >= 15 and set(got) == {("trajectory_msgs/msg/JointTrajectory", I.TOPIC_COMMAND)}, got


def test_recorder_never_overwrites_an_existing_file_or_directory(tmp_path):
    """A recorder restarted with a crashed run's output name must not truncate that recording."""
    crashed = tmp_path / "run.mcap"
    crashed.write_bytes(b"the crash's recording")
    for target, what in ((crashed, "an existing file"), (tmp_path, "a directory")):
        rec = _start("bimacppo_bag.recorder", str(target))
        out, _ = rec.communicate(timeout=PROC_TIMEOUT)
        assert rec.returncode == 2 and "Traceback" not in out, out
        assert f"is {what}: refusing to overwrite" in out, out
    assert crashed.read_bytes() == b"the crash's recording"


@pytest.mark.parametrize("map_kind", ["id", "file"])
def test_recording_of_a_world_names_its_map_and_renders_on_it(map_kind, tmp_path, capsys):
    """The recorder asks the world's parameter service which map it runs on: a world on
    single_lane_4way (not the default; by id, or a copy of its file) gives a bag whose
    ``bimacppo`` record names it (a file with its text), and render-bag without --map draws the
    recording on that road, a file's also once the file is gone."""
    from bimacppo_sim.road import MAP_DIR
    map_id, expected = "single_lane_4way", {mcap_io.MAP_ID_KEY: "single_lane_4way"}
    if map_kind == "file":
        text = (MAP_DIR / "single_lane_4way.yaml").read_text()
        map_file = tmp_path / "junction.yaml"
        map_file.write_text(text)
        map_id, expected = str(map_file), {mcap_io.MAP_ID_KEY: str(map_file), mcap_io.MAP_YAML_KEY: text}
    path, gif = tmp_path / "world.mcap", tmp_path / "world.gif"
    rec = _start("bimacppo_bag.recorder", str(path), "--ros-args", "-p", "discovery_period_s:=0.1",
                 "-p", "flush_period_s:=0.1")
    world = _start("bimacppo_sim.ros.world_node", "--ros-args", "-p", f"map_id:={map_id}",
                   "-p", "resend_period_s:=0.1")
    t_end = time.monotonic() + PROC_TIMEOUT
    while time.monotonic() < t_end:   # until the file holds the map record and a state
        report = mcap_io.ReadReport()
        states = sum(1 for _ in mcap_io.iter_mcap(path, report, topics=[I.TOPIC_EGO_ODOM]))
        if states and mcap_io.RUN_METADATA in report.metadata:
            break
        time.sleep(0.2)
    rc_world, out_world = _stop(world)
    rc, out = _stop(rec, signal.SIGTERM)
    assert rc == 0 and rc_world == 0 and "Traceback" not in out + out_world, out + out_world
    assert f"the world runs on map {map_id}: recorded" in out, out
    report = mcap_io.ReadReport()
    assert any(True for _ in mcap_io.iter_mcap(path, report, topics=[I.TOPIC_EGO_ODOM]))
    assert report.complete, report.error
    assert report.metadata[mcap_io.RUN_METADATA] == expected

    from bimacppo_sim.cli import main
    from PIL import Image

    def render(*args):
        assert main(["render-bag", str(path), "-o", str(gif), "--max-frames", "2", "--overwrite", *args]) == 0
        return np.asarray(Image.open(gif).convert("RGB"))
    explicit = render("--map", map_id)
    if map_kind == "file":
        map_file.unlink()
    capsys.readouterr()
    recorded = render()
    printed = capsys.readouterr()
    assert f"on map {map_id};" in printed.out and "warning" not in printed.err, printed
    assert np.array_equal(recorded, explicit)
    assert not np.array_equal(recorded, render("--map", "dual_lane_4way"))


def test_recorder_killed_leaves_readable_prefix(node, tmp_path):
    # last in this file on purpose: a SIGKILLed participant lingers in DDS discovery (and its
    # shared-memory ports) for seconds, which would disturb the tests after it
    path = tmp_path / "killed.mcap"
    flush_s = 0.2
    rec, odom, goal = _record(node, path, 0, extra=("-p", f"flush_period_s:={flush_s}",
                                                    "-p", "chunk_size:=4096"))
    # sentinels (x = -1) until one is on disk: from then on the recorder receives for sure,
    # however long DDS took to match it on a loaded machine
    t_end = time.monotonic() + PROC_TIMEOUT
    while time.monotonic() < t_end and not any(True for _ in mcap_io.iter_mcap(path, topics=[I.TOPIC_EGO_ODOM])):
        odom.publish(I.state_to_odometry([-1.0, 1.0, 2.0, 0.1], 1))
        _spin(node, 0.05)
    for k in range(100):
        odom.publish(I.state_to_odometry([float(k), 1.0, 2.0, 0.1], k + 2))
        _spin(node, 0.002)
    _spin(node, 1.5)  # several flush periods: the first 100 messages are on disk
    for k in range(100, 160):  # the tail, still in the open chunk when the kill comes
        odom.publish(I.state_to_odometry([float(k), 1.0, 2.0, 0.1], k + 2))
    rc, _ = _stop(rec, signal.SIGKILL)
    node.destroy_publisher(odom)
    node.destroy_publisher(goal)
    assert rc == -signal.SIGKILL
    report = mcap_io.ReadReport()
    xs = []
    from mcap_ros2.decoder import DecoderFactory
    dec = DecoderFactory()
    for sch, ch, m in mcap_io.iter_mcap(path, report, topics=[I.TOPIC_EGO_ODOM]):
        x = dec.decoder_for("cdr", sch)(m.data).pose.pose.position.x
        if x >= 0.0:
            xs.append(x)
    assert not report.complete  # no summary: it was killed
    assert len(xs) >= 100, report
    assert xs == [float(k) for k in range(len(xs))], report  # a prefix, nothing out of order or garbled
