"""Live-view scene (bimacppo_viz.scene): graph states -> Foxglove messages, decoded back with
the schemas the channels advertise; the shipped layout opens exactly the scene's channels."""
import json
import math

import numpy as np
import pytest

pytest.importorskip("foxglove")

from bimacppo_viz import layout_path  # noqa: E402
from bimacppo_viz import scene as S  # noqa: E402
from vizlib import decode, protobuf_class  # noqa: E402


class Style:
    """The attributes the scene reads from interfaces.MarkerStyle (values chosen to be told apart)."""
    length, width, height = 4.0, 2.0, 1.2
    ego_rgba = (0.0, 0.0, 1.0, 1.0)
    sv_rgba = (1.0, 0.0, 0.0, 1.0)
    goal_rgba = (0.0, 1.0, 0.0, 1.0)
    route_rgba = (0.5, 0.5, 0.5, 1.0)
    reference_rgba = (1.0, 0.0, 1.0, 1.0)
    line_width = 0.3


def _yaw(q):
    return 2.0 * math.atan2(q.z, q.w)


def test_frames_are_the_contracts():
    I = pytest.importorskip("bimacppo_interfaces.contract")
    assert (S.FRAME_MAP, S.FRAME_EGO, S.FRAME_REFERENCE) == (I.FRAME_MAP, I.FRAME_BASE, I.FRAME_REFERENCE)
    for yaw in (-3.0, -0.4, 0.0, 2.5, math.pi):   # the same yaw-only quaternion as the messages carry
        q, r = decode(S.yaw_quaternion(yaw)), I.yaw_to_quaternion(yaw)
        assert (q.x, q.y, q.z, q.w) == pytest.approx((r.x, r.y, r.z, r.w))


def test_vehicles_update_replaces_all_entities_with_ev_and_svs():
    ego = [1.0, -2.0, 3.5, 0.7]
    svs = [[10.0, 1.75, 5.0, -1.2], [-3.0, 20.0, 0.0, 3.0]]
    d = decode(S.vehicles_update(ego, ["sv0", "sv7"], svs, 12_300_000_000, Style))
    assert [x.type for x in d.deletions] == [1]          # SceneEntityDeletionType.All
    assert [e.id for e in d.entities] == ["ego", "sv/sv0", "sv/sv7"]
    for e, state, rgba in zip(d.entities, [ego, *svs], [Style.ego_rgba] + [Style.sv_rgba] * 2):
        assert e.frame_id == "map"
        assert (e.timestamp.seconds, e.timestamp.nanos) == (12, 300_000_000)
        cube = e.cubes[0]
        assert (cube.pose.position.x, cube.pose.position.y) == pytest.approx(state[:2])
        assert cube.pose.position.z == pytest.approx(0.5 * Style.height)
        assert _yaw(cube.pose.orientation) == pytest.approx(state[3])
        assert (cube.size.x, cube.size.y, cube.size.z) == pytest.approx((Style.length, Style.width, Style.height))
        assert (cube.color.r, cube.color.g, cube.color.b) == pytest.approx(rgba[:3])
    assert "3.5" in d.entities[0].texts[0].text and d.entities[2].texts[0].text == "sv7"


def test_vehicles_update_without_svs_and_bad_inputs():
    d = decode(S.vehicles_update([0, 0, 0, 0], [], np.zeros((0, 4)), 0, Style))
    assert [e.id for e in d.entities] == ["ego"]
    with pytest.raises(ValueError, match="2 SV ids but 1"):
        S.vehicles_update([0, 0, 0, 0], ["a", "b"], [[0, 0, 0, 0]], 0, Style)
    with pytest.raises(ValueError, match="non-finite"):
        S.vehicles_update([0, 0, 0, 0], ["a"], [[0, float("nan"), 0, 0]], 0, Style)
    with pytest.raises(ValueError, match="ego"):
        S.vehicles_update([0, 0, float("inf"), 0], [], [], 0, Style)
    with pytest.raises(ValueError, match="stamp"):
        S.vehicles_update([0, 0, 0, 0], [], [], -1, Style)


def test_route_goal_reference_and_transforms():
    route = np.array([[0.0, -40.0, 1.57], [0.0, -20.0, 1.57], [5.0, 0.0, 0.8]])
    d = decode(S.route_update(route, 100, Style))
    line = d.entities[0].lines[0]
    assert d.entities[0].id == "route"
    assert [(p.x, p.y) for p in line.points] == [(0.0, -40.0), (0.0, -20.0), (5.0, 0.0)]
    assert line.thickness == pytest.approx(Style.line_width)
    with pytest.raises(ValueError, match="route"):
        S.route_update([[1.0, 2.0]], 0, Style)

    g = decode(S.goal_update([-30.0, 1.75, math.pi], 5, Style)).entities[0]
    assert g.id == "goal" and (g.arrows[0].pose.position.x, g.arrows[0].pose.position.y) == (-30.0, 1.75)
    assert abs(_yaw(g.arrows[0].pose.orientation)) == pytest.approx(math.pi)
    with pytest.raises(ValueError, match="goal"):
        S.goal_update([1.0, 2.0], 0, Style)

    r = decode(S.reference_update([2.0, 3.0, 6.25, -0.4], 5, Style)).entities[0]
    assert r.id == "x_imr" and _yaw(r.arrows[0].pose.orientation) == pytest.approx(-0.4)
    assert "6.2" in r.texts[0].text

    tf = decode(S.transform("base_link", [4.0, 5.0, 1.0, 0.3], 2_000_000_001))
    assert (tf.parent_frame_id, tf.child_frame_id) == ("map", "base_link")
    assert (tf.translation.x, tf.translation.y, tf.translation.z) == (4.0, 5.0, 0.0)
    assert _yaw(tf.rotation) == pytest.approx(0.3)
    assert (tf.timestamp.seconds, tf.timestamp.nanos) == (2, 1)


def test_road_draws_every_lane_connectors_fainter():
    from bimacppo_sim import load_map
    road = load_map("dual_lane_4way")
    lanes = [(ln.kind, ln.points) for ln in road.lanes.values()]
    d = decode(S.road_update(lanes))
    assert [e.id for e in d.entities] == ["road"]
    lines = d.entities[0].lines
    assert len(lines) == len(lanes)
    for line, (kind, pts) in zip(lines, lanes):
        assert np.array([(p.x, p.y) for p in line.points]) == pytest.approx(np.asarray(pts)[:, :2])
        assert line.color.a == pytest.approx((S.CONNECTOR_RGBA if kind == "conn" else S.LANE_RGBA)[3])
    assert {ln.color.a for ln in lines} == {S.CONNECTOR_RGBA[3], S.LANE_RGBA[3]}
    with pytest.raises(ValueError, match="lane 1"):
        S.road_update([("in", [[0, 0], [1, 1]]), ("in", [[0, float("nan")], [1, 1]])])


def test_json_messages_for_the_plots():
    assert S.state_json([1, 2, 3, 0.5], 1_500_000_000) == {"t": 1.5, "x": 1.0, "y": 2.0, "v": 3.0, "psi": 0.5}
    c = S.command_json([0.8, -0.05], [[0.8, -0.05], [0.6, -0.02], [0.1, 0.0]], 200_000_000)
    assert c == {"t": 0.2, "a": 0.8, "delta": -0.05, "horizon_a": [0.8, 0.6, 0.1],
                 "horizon_delta": [-0.05, -0.02, 0.0]}
    with pytest.raises(ValueError, match="non-finite"):
        S.command_json([float("nan"), 0.0], [[0.0, 0.0]], 0)
    e = S.episode_json({"outcome": "collision", "collided_with": "sv2"}, 3_000_000_000)
    assert e["outcome"] == "collision" and e["values"]["collided_with"] == "sv2" and e["t"] == 3.0
    assert e["source"] == S.SOURCE_WORLD and "return" not in e    # the world's result has no return
    r = S.episode_json({"outcome": "success", "return": "12.5"}, 3_000_000_000, S.SOURCE_PLANNER, 12.5)
    assert r["source"] == S.SOURCE_PLANNER and r["return"] == 12.5 and r["values"]["return"] == "12.5"
    for name, schema in S.JSON_SCHEMAS.items():   # every JSON message fits its advertised schema's fields
        msgs = {S.CH_EGO: [S.state_json([0, 0, 0, 0], 0)], S.CH_REFERENCE_STATE: [S.state_json([0, 0, 0, 0], 0)],
                S.CH_COMMAND: [c], S.CH_EPISODE: [e, r]}[name]
        for msg in msgs:
            assert set(schema.get("required", schema["properties"])) <= set(msg) <= set(schema["properties"]), name
    assert set(r) == set(S.JSON_SCHEMAS[S.CH_EPISODE]["properties"])
    assert S.JSON_SCHEMAS[S.CH_EPISODE]["properties"]["source"]["enum"] == list(S.EPISODE_SOURCES)


def test_episode_return_is_a_finite_number_from_a_known_source():
    assert S.episode_json({}, 0, S.SOURCE_PLANNER, -3)["return"] == -3.0
    assert isinstance(S.episode_json({}, 0, S.SOURCE_PLANNER, -3)["return"], float)
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="return is not finite"):
            S.episode_json({"outcome": "success"}, 0, S.SOURCE_PLANNER, bad)
    with pytest.raises(ValueError, match="source must be one of"):
        S.episode_json({"outcome": "success"}, 0, "curriculum", 1.0)


def _read_mcap(path):
    """{topic: [decoded message, ...]} of an MCAP the foxglove SDK wrote (protobuf and JSON)."""
    from mcap.reader import make_reader
    out = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        classes = {}
        for schema, channel, message in reader.iter_messages():
            if channel.message_encoding == "json":
                value = json.loads(message.data)
            else:
                if schema.id not in classes:
                    classes[schema.id] = protobuf_class(schema.name, schema.data)
                value = classes[schema.id].FromString(message.data)
            out.setdefault(channel.topic, []).append(value)
    return out


def test_live_scene_pairs_ev_and_svs_by_stamp(tmp_path):
    import foxglove
    ctx = foxglove.Context()
    path = tmp_path / "scene.mcap"
    writer = foxglove.open_mcap(str(path), context=ctx)
    sc = S.LiveScene(ctx, Style)
    sc.on_state([0.0, -40.0, 5.0, 1.57], 100)           # no /objects yet: the EV alone
    sc.on_objects(["a"], [[10.0, 0.0, 3.0, 3.14]], 100)  # tick 100 complete: redrawn with the SV
    sc.on_objects(["a"], [[9.7, 0.0, 3.0, 3.14]], 200)   # SVs of tick 200 before its EV: wait
    sc.on_state([0.0, -39.5, 5.0, 1.57], 200)            # pair of tick 200
    sc.on_state([0.0, -39.0, 5.0, 1.57], 300)            # EV of 300, SVs still of 200: wait
    sc.on_reference([0.0, -30.0, 6.0, 1.57], 100)
    sc.on_goal([-60.0, 1.75, 3.14], 100)
    sc.on_route([[0.0, -40.0], [0.0, 0.0]], 100)
    sc.on_command([1.0, 0.0], [[1.0, 0.0], [0.5, 0.01]], 100)
    sc.on_result({"outcome": "success", "stamp_ns": "300"}, 300)
    sc.on_result({"outcome": "success", "stamp_ns": "300", "return": "-4.25"}, 300, S.SOURCE_PLANNER, -4.25)
    sc.on_road([("in", [[0.0, -60.0], [0.0, -15.0]]), ("conn", [[0.0, -15.0], [-15.0, 0.0]])])
    sc.resend_latched()                                 # map and goal again, for a later client
    writer.close()
    got = _read_mcap(path)
    vehicles = got[S.CH_VEHICLES]
    assert [[e.id for e in u.entities] for u in vehicles] == [["ego"], ["ego", "sv/a"], ["ego", "sv/a"]]
    assert [u.entities[0].timestamp.nanos for u in vehicles] == [100, 100, 200]
    assert vehicles[2].entities[1].cubes[0].pose.position.x == pytest.approx(9.7)
    assert [m["y"] for m in got[S.CH_EGO]] == [-40.0, -39.5, -39.0]
    frames = [t.transforms[0].child_frame_id for t in got[S.CH_TF]]
    assert frames.count("base_link") == 3 and frames.count("x_imr") == 1
    assert got[S.CH_COMMAND][0]["horizon_a"] == [1.0, 0.5]
    assert [(m["source"], m["outcome"], m.get("return")) for m in got[S.CH_EPISODE]] == [
        (S.SOURCE_WORLD, "success", None), (S.SOURCE_PLANNER, "success", -4.25)]
    assert got[S.CH_EPISODE][1]["t"] == pytest.approx(3e-7)
    assert len(got[S.CH_ROUTE]) == len(got[S.CH_REFERENCE]) == 1
    assert len(got[S.CH_GOAL]) == 2 and got[S.CH_GOAL][0] == got[S.CH_GOAL][1]
    assert sc.logged[S.CH_VEHICLES] == 3
    assert len(got[S.CH_ROAD]) == 2 and got[S.CH_ROAD][0] == got[S.CH_ROAD][1]
    assert len(got[S.CH_ROAD][0].entities[0].lines) == 2


def test_shipped_layout_opens_the_scene_channels_and_plots():
    layout = json.loads(open(layout_path()).read())
    panels = layout["configById"]
    three_d = [v for k, v in panels.items() if k.startswith("3D!")]
    assert len(three_d) == 1
    assert set(three_d[0]["topics"]) == set(S.SCENE_CHANNELS)
    assert all(t["visible"] for t in three_d[0]["topics"].values())
    plotted = {p["value"] for k, v in panels.items() if k.startswith("Plot!") for p in v["paths"]}
    assert plotted == {f"{S.CH_EGO}.v", f"{S.CH_REFERENCE_STATE}.v", f"{S.CH_COMMAND}.a", f"{S.CH_COMMAND}.delta",
                       f"{S.CH_EPISODE}.return"}
    for path in plotted:    # each plotted field is a property of its channel's JSON schema
        channel, fld = path.rsplit(".", 1)
        assert fld in S.JSON_SCHEMAS[channel]["properties"]

    def leaves(node):
        if isinstance(node, str):
            return [node]
        return leaves(node["first"]) + leaves(node["second"])
    assert sorted(leaves(layout["layout"])) == sorted(panels)   # every configured panel is placed


def test_live_view_node_reads_results_through_the_contract():
    """The node's result callbacks (called without DDS): the planner's result gives the scene its
    return as the contract decodes it; one without a return is rejected; the world's has none."""
    import types
    pytest.importorskip("rclpy")
    I = pytest.importorskip("bimacppo_interfaces.contract")
    from bimacppo_viz.ros.live_view import TOPIC_PARAMETERS, LiveViewNode
    assert TOPIC_PARAMETERS["planner_result_topic"] == I.TOPIC_PLANNER_RESULT
    assert TOPIC_PARAMETERS["result_topic"] == I.TOPIC_RESULT
    calls = []
    fake = types.SimpleNamespace(scene=types.SimpleNamespace(on_result=lambda *a: calls.append(a)))
    ret = -7.125
    planner = I.result_to_status(I.EpisodeResult("collision", ret, 2, "left", 4, 80, 8_000_000_000))
    world = I.result_to_status(I.EpisodeResult("collision", None, 2, "left", 4, 80, 8_000_000_000))
    LiveViewNode._planner_result(fake, planner)
    LiveViewNode._result(fake, world)
    (pv, ps, psrc, pret), (wv, ws, wsrc) = calls
    assert (ps, psrc, pret) == (8_000_000_000, S.SOURCE_PLANNER, ret) and pv["return"] == repr(ret)
    assert (ws, wsrc) == (8_000_000_000, S.SOURCE_WORLD) and "return" not in wv
    assert S.episode_json(pv, ps, psrc, pret)["return"] == ret
    with pytest.raises(I.MessageError, match="no return"):
        LiveViewNode._planner_result(fake, world)
    assert len(calls) == 2
