"""The live view over real DDS and a real WebSocket: the node (a separate process, this test's ROS
domain) serves what a publisher here sends; a client written from RFC 6455 (tests/vizlib.py)
checks the advertised channels and decodes the messages that arrive. Also: a port in use, a bad
parameter, and ``bimacppo-graph --live-view``."""
import json
import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")
pytest.importorskip("foxglove")
pytestmark = pytest.mark.ros

from bimacppo_interfaces import contract as I  # noqa: E402
from bimacppo_viz import scene as S  # noqa: E402
from vizlib import OP_BINARY, OP_TEXT, WsClient, message_data, protobuf_class  # noqa: E402

ENV = dict(os.environ, AMENT_PREFIX_PATH=os.environ.get("AMENT_PREFIX_PATH", sys.prefix))
PROC_TIMEOUT = 30
SCHEMA_NAMES = {**{c: "foxglove.SceneUpdate" for c in S.SCENE_CHANNELS}, S.CH_TF: "foxglove.FrameTransforms"}


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(*args):
    return subprocess.Popen([sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True, env=ENV)


def _stop(proc):
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
    try:
        out, _ = proc.communicate(timeout=PROC_TIMEOUT)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        pytest.fail(f"process did not stop: {out}")
    return proc.returncode, out


def _connect(port, proc, timeout=PROC_TIMEOUT):
    """A WebSocket client on the server once it listens (fails early if the process died)."""
    t_end = time.monotonic() + timeout
    while True:
        if proc.poll() is not None:
            pytest.fail(f"server process exited ({proc.returncode}): {proc.communicate()[0]}")
        try:
            return WsClient("127.0.0.1", port)
        except OSError:
            if time.monotonic() > t_end:
                pytest.fail(f"nothing listens on port {port} after {timeout} s")
            time.sleep(0.2)


def _handshake(client):
    """serverInfo, then advertise: returns {topic: channel} of the advertised channels."""
    assert " 101 " in client.response.splitlines()[0], client.response
    assert "sec-websocket-protocol: foxglove." in client.response.lower()
    op, data = client.recv()
    info = json.loads(data)
    assert op == OP_TEXT and info["op"] == "serverInfo" and info["name"] == "bimacppo"
    channels = {}
    while set(channels) != set(S.CHANNELS):
        _, data = client.recv_until(lambda o, d: o == OP_TEXT and json.loads(d)["op"] == "advertise", 10)
        channels.update({c["topic"]: c for c in json.loads(data)["channels"]})
    return channels


def _subscribe(client, channels):
    subs = {i: channels[t] for i, t in enumerate(sorted(channels))}
    client.send_json({"op": "subscribe", "subscriptions": [{"id": i, "channelId": c["id"]} for i, c in subs.items()]})
    return subs


def _decoder(channel):
    if channel["encoding"] == "json":
        return json.loads
    import base64
    cls = protobuf_class(channel["schemaName"], base64.b64decode(channel["schema"]))
    return cls.FromString


def _collect(client, subs, want, timeout, tick=None, enough=None):
    """Decoded messages per topic until every topic of ``want`` has one (and ``enough(got)``, if
    given, holds); ``tick()`` runs between frames."""
    decoders = {i: _decoder(c) for i, c in subs.items()}
    got = {}
    t_end = time.monotonic() + timeout
    while not (want <= set(got) and (enough is None or enough(got))):
        if time.monotonic() > t_end:
            pytest.fail(f"no message on {sorted(want - set(got))} within {timeout} s (got {sorted(got)})")
        if tick is not None:
            tick()
        try:
            op, data = client.recv_until(lambda o, d: o == OP_BINARY, 0.3)
        except TimeoutError:
            continue
        sub, _, payload = message_data(data)
        got.setdefault(subs[sub]["topic"], []).append(decoders[sub](payload))
    return got


@pytest.fixture(scope="module")
def node():
    rclpy.init()
    n = rclpy.create_node("test_live_view")
    yield n
    n.destroy_node()
    rclpy.try_shutdown()


def test_live_view_serves_the_graph_topics(node):
    port = _free_port()
    pubs = {
        "odom": node.create_publisher(I.Odometry, I.TOPIC_EGO_ODOM, I.STATE_QOS),
        "objects": node.create_publisher(I.MultiDOFJointTrajectory, I.TOPIC_OBJECTS, I.STATE_QOS),
        "goal": node.create_publisher(I.PoseStamped, I.TOPIC_GOAL, I.LATCHED_QOS),
        "reference": node.create_publisher(I.Odometry, I.TOPIC_REFERENCE, I.STATE_QOS),
        "command": node.create_publisher(I.JointTrajectory, I.TOPIC_COMMAND, I.STATE_QOS),
        "result": node.create_publisher(I.DiagnosticStatus, I.TOPIC_RESULT, I.RESULT_QOS),
        "planner_result": node.create_publisher(I.DiagnosticStatus, I.TOPIC_PLANNER_RESULT, I.RESULT_QOS),
    }
    pubs["goal"].publish(I.goal_to_pose([-60.0, 1.75, 3.1], 100_000_000))   # latched: sent before the view starts
    proc = _start("-m", "bimacppo_viz.ros.live_view", "--ros-args", "-p", f"port:={port}")
    try:
        client = _connect(port, proc)
        channels = _handshake(client)
        assert set(channels) == set(S.CHANNELS)
        for topic, name in SCHEMA_NAMES.items():
            assert channels[topic]["schemaName"] == name and channels[topic]["encoding"] == "protobuf", topic
        for topic in S.JSON_CHANNELS:
            assert channels[topic]["encoding"] == "json"
        subs = _subscribe(client, channels)
        k = [0]

        def tick():   # one tick of a stand-in world and its planner/controller, every call
            k[0] += 1
            stamp = k[0] * 100_000_000
            ego = [0.0, -40.0 + k[0], 5.0, 1.57]
            pubs["odom"].publish(I.state_to_odometry(ego, stamp))
            pubs["objects"].publish(I.svs_to_objects(["sv0"], [[20.0, 1.75, 4.0, 3.14]], stamp))
            pubs["reference"].publish(I.reference_to_odometry([0.0, -30.0 + k[0], 6.0, 1.57], stamp))
            pubs["command"].publish(I.command_to_trajectory([0.5, -0.02], stamp, horizon=[[0.5, -0.02], [0.4, 0.0]],
                                                            dt=0.1))
            if k[0] % 5 == 0:   # an episode ends: the world's result, then the planner's with the return
                res = I.EpisodeResult("timeout", None, 1, "left", 3, k[0], stamp)
                pubs["result"].publish(I.result_to_status(res))
                pubs["planner_result"].publish(I.result_to_status(
                    I.EpisodeResult(res.outcome, -0.5 * k[0], res.n_sv, res.task, res.seed, res.steps, stamp)))
            rclpy.spin_once(node, timeout_sec=0.0)

        want = {S.CH_ROAD, S.CH_VEHICLES, S.CH_GOAL, S.CH_REFERENCE, S.CH_TF, S.CH_EGO, S.CH_COMMAND, S.CH_EPISODE}
        sources = lambda got: {m["source"] for m in got.get(S.CH_EPISODE, [])} == set(S.EPISODE_SOURCES)  # noqa: E731
        got = _collect(client, subs, want, PROC_TIMEOUT, tick, enough=sources)
        client.close()
    finally:
        rc, out = _stop(proc)
    assert rc == 0 and "Traceback" not in out, out
    assert f"ws://127.0.0.1:{port}" in out
    # what arrived is what was published, through the converters; the road is the default map's
    from bimacppo_sim import load_map
    assert len(got[S.CH_ROAD][0].entities[0].lines) == len(load_map("dual_lane_4way").lanes)
    goal = got[S.CH_GOAL][0].entities[0].arrows[0].pose.position
    assert (goal.x, goal.y) == (-60.0, 1.75)
    paired = [u for u in got[S.CH_VEHICLES] if len(u.entities) == 2]
    assert paired, "no EV + SV update"
    ev, sv = paired[0].entities
    assert (ev.id, sv.id) == ("ego", "sv/sv0")
    tick_k = round(ev.timestamp.seconds * 10 + ev.timestamp.nanos / 1e8)
    assert ev.cubes[0].pose.position.y == pytest.approx(-40.0 + tick_k)
    assert sv.cubes[0].pose.position.x == pytest.approx(20.0)
    ego = got[S.CH_EGO][0]
    assert ego["v"] == pytest.approx(5.0) and ego["y"] == pytest.approx(-40.0 + round(ego["t"] * 10))
    cmd = got[S.CH_COMMAND][0]
    assert (cmd["a"], cmd["delta"]) == pytest.approx((0.5, -0.02)) and cmd["horizon_a"] == pytest.approx([0.5, 0.4])
    for m in got[S.CH_EPISODE]:   # the planner's results carry the return it sent (-0.5 per step), the world's none
        assert m["outcome"] == "timeout" and m["values"]["task"] == "left"
        steps = int(m["values"]["steps"])
        assert m["t"] == pytest.approx(steps / 10)
        if m["source"] == S.SOURCE_PLANNER:
            assert m["return"] == pytest.approx(-0.5 * steps)
        else:
            assert "return" not in m


def test_road_lanes_are_placed_by_the_map_pose(tmp_path):
    import yaml

    from bimacppo_sim import load_map
    from bimacppo_sim.road import MAP_DIR
    from bimacppo_viz.ros.live_view import road_lanes
    plain = load_map("single_lane_4way")
    spec = yaml.safe_load((MAP_DIR / "single_lane_4way.yaml").read_text())
    spec["pose"] = {"x": 412.0, "y": -318.5, "heading": 0.6}
    (tmp_path / "posed.yaml").write_text(yaml.safe_dump(spec))
    posed = load_map(str(tmp_path / "posed.yaml"))
    a, b = road_lanes(plain), road_lanes(posed)
    assert [k for k, _ in a] == [ln.kind for ln in plain.lanes.values()] == [k for k, _ in b]
    for (_, pa), ln in zip(a, plain.lanes.values()):
        assert np.allclose(pa, ln.points[:, :2])                 # at the origin: the map's own points
    c, s = np.cos(0.6), np.sin(0.6)
    for (_, pa), (_, pb) in zip(a, b):
        moved = np.c_[412.0 + c * pa[:, 0] - s * pa[:, 1], -318.5 + s * pa[:, 0] + c * pa[:, 1]]
        assert np.allclose(pb, moved)


def test_port_in_use_and_bad_parameters_are_one_line_errors():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        proc = _start("-m", "bimacppo_viz.ros.live_view", "--ros-args", "-p", f"port:={port}")
        rc, out = _stop_when_done(proc)
    assert rc == 2 and "Traceback" not in out, out
    errors = [ln for ln in out.splitlines() if ln.startswith("error:")]
    assert len(errors) == 1 and f"127.0.0.1:{port}" in errors[0] and "in use" in errors[0], out
    for param, word in (("port:=70000", "port"), ("map_id:=nowhere", "map_id"), ("host:=", "host"),
                        ("ego_topic:=bad topic", "ego_topic")):
        proc = _start("-m", "bimacppo_viz.ros.live_view", "--ros-args", "-p", param)
        rc, out = _stop_when_done(proc)
        errors = [ln for ln in out.splitlines() if ln.startswith("error:")]
        assert rc == 2 and "Traceback" not in out and len(errors) == 1 and word in errors[0], out


def _stop_when_done(proc):
    try:
        out, _ = proc.communicate(timeout=PROC_TIMEOUT)
    except subprocess.TimeoutExpired:
        return _stop(proc)
    return proc.returncode, out


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory):
    from bimacppo_learning.checkpoint import export_policy
    from bimacppo_learning.ppo import PPO
    path = tmp_path_factory.mktemp("policy") / "policy.pt"
    export_policy(PPO(16, (5, 5, 3), seed=1), path)
    return path


def test_graph_live_view_flag_shows_the_running_graph(policy_file, tmp_path):
    """``bimacppo-graph --live-view PORT``: the view serves the real graph, which records as usual;
    the recording (our recorder's) renders with ``bimacppo-sim render-bag``."""
    port = _free_port()
    mcap, gif = tmp_path / "run.mcap", tmp_path / "run.gif"
    proc = _start("-m", "bimacppo_bringup.graph", "--episodes", "1", "--scheduler", "fixed",
                  "--policy", str(policy_file), "--output", str(mcap), "--timeout", "90", "--live-view", str(port))
    try:
        client = _connect(port, proc, timeout=60)
        channels = _handshake(client)
        subs = _subscribe(client, channels)
        got = _collect(client, subs, {S.CH_VEHICLES, S.CH_ROUTE, S.CH_REFERENCE, S.CH_COMMAND, S.CH_GOAL}, 90)
        client.close()
        rc, out = _stop_when_done(proc)
    finally:
        if proc.poll() is None:
            _stop(proc)
    assert "Traceback" not in out, out
    assert rc == 0 and "episodes: 1" in out, out
    route = got[S.CH_ROUTE][0].entities[0].lines[0].points
    assert len(route) >= 2
    ev = got[S.CH_VEHICLES][-1].entities[0]
    assert ev.id == "ego" and np.isfinite(ev.cubes[0].pose.position.x)
    r = subprocess.run([sys.executable, "-m", "bimacppo_sim.cli", "render-bag", str(mcap), "-o", str(gif),
                        "--every", "5"], capture_output=True, text=True, env=ENV, timeout=300)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stdout + r.stderr
    assert "(" in r.stdout and f"wrote {gif}" in r.stdout and "no episode result" not in r.stdout, r.stdout
    assert gif.stat().st_size > 0
