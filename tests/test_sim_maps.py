"""Road maps: loading/validation, lane graph + A*, drivable area, Fig. 3 conflict counts."""
import math

import numpy as np
import pytest
import yaml

from bimacppo_common.conventions import TASKS
from bimacppo_sim import load_map
from bimacppo_sim.road import MAP_DIR


@pytest.mark.parametrize("mid", ["dual_lane_4way", "single_lane_4way", "three_lane_straight"])
def test_maps_load_and_are_cached(mid):
    a = load_map(mid)
    assert a is load_map(mid)
    assert a.id == mid
    assert a.lanes


def test_unknown_map_id_names_it_and_lists_available():
    with pytest.raises(ValueError, match="unknown map id 'nowhere'.*dual_lane_4way"):
        load_map("nowhere")


def _write(tmp_path, **changes):
    spec = yaml.safe_load((MAP_DIR / "dual_lane_4way.yaml").read_text())
    spec.update(changes)
    spec = {k: v for k, v in spec.items() if v is not None}
    p = tmp_path / "m.yaml"
    p.write_text(yaml.safe_dump(spec))
    return p


@pytest.mark.parametrize("changes, msg", [
    ({"lane_width": -1.0}, "lane_width"),
    ({"lane_width": "wide"}, "lane_width"),
    ({"color": "red"}, "unknown key"),
    ({"type": "roundabout"}, "type"),
    ({"max_sv": 4}, "max_sv"),
    ({"sv_arms": ["north", "south"]}, "sv_arms"),
    ({"turns": {"left": [[0, 0]], "straight": [[0, 5]], "right": [[1, 1]]}}, "turns.straight"),
    ({"arm_length": None}, "arm_length"),
])
def test_malformed_map_files_fail_naming_the_problem(tmp_path, changes, msg):
    with pytest.raises(ValueError, match=msg):
        load_map(_write(tmp_path, **changes))


def test_broken_yaml_and_missing_file(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("id: [unclosed\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        load_map(p)
    with pytest.raises(ValueError, match="not found"):
        load_map(tmp_path / "missing.yaml")


def test_dual_lane_geometry_matches_spec():
    r = load_map("dual_lane_4way")
    assert r.n_lanes == 2 and r.lane_width == 3.5
    # inner northbound lane of the south arm sits 1.75 m east of the centre line
    ln = r.lanes["south_in_0"]
    assert np.allclose(ln.points[:, 0], 1.75)
    assert math.isclose(ln.heading, math.pi / 2)
    assert r.lanes["south_in_1"].left == "south_in_0"
    assert r.lanes["south_in_0"].right == "south_in_1" and r.lanes["south_in_0"].left is None


def test_drivable_area():
    r = load_map("dual_lane_4way")
    assert r.drivable(0.0, 0.0)
    assert r.drivable(6.9, -40.0)
    assert not r.drivable(7.1, -40.0)                         # beside the road
    assert not r.drivable(r.H - 0.2, r.H - 0.2)               # inside the kerb fillet
    assert r.drivable(r.half_road + 0.1, r.half_road + 0.1)   # junction corner near the lanes
    s = load_map("three_lane_straight")
    assert s.drivable(-5.0, 0.0) and not s.drivable(-5.5, 0.0)


def test_lateral_point():
    r = load_map("dual_lane_4way")
    p = r.lateral_point(1.75, -40.0, math.pi / 2, +1)      # right of the inner lane: outer lane
    assert np.allclose(p, [5.25, -40.0, math.pi / 2])
    assert r.lateral_point(1.75, -40.0, math.pi / 2, -1) is None     # left of inner = oncoming
    assert r.lateral_point(0.0, 0.0, 0.0, 1) is None                  # junction
    assert r.lateral_point(1.75, -40.0, -math.pi / 2, 1) is None      # driving against the lane
    s = load_map("three_lane_straight")
    assert np.allclose(s.lateral_point(0.0, 10.0, math.pi / 2, -1)[:2], [-3.5, 10.0])
    with pytest.raises(ValueError, match="side"):
        r.lateral_point(1.75, -40.0, math.pi / 2, 0)


def test_astar_changes_lane_before_the_junction_for_a_left_turn_from_the_outer_lane():
    r = load_map("dual_lane_4way")
    pts, conns, n_lc = r.plan_route("south_in_1", 30.0, "west_out_0", 20.0)
    assert conns == ["south_in_0>west_out_0"]
    assert n_lc == 1
    # the lane change is complete before the no-lane-change zone at the junction edge
    on_approach = pts[pts[:, 1] < -r.H]
    after = on_approach[on_approach[:, 1] > -r.H - r.cfg.no_lane_change_zone]
    assert np.allclose(after[:, 0], 1.75)
    assert np.allclose(pts[-1], r.lane_point("west_out_0", 20.0)[:2])


def test_astar_no_lane_change_when_already_right():
    r = load_map("dual_lane_4way")
    _, conns, n_lc = r.plan_route("south_in_1", 30.0, "east_out_1", 20.0)
    assert conns == ["south_in_1>east_out_1"] and n_lc == 0


# Paper Fig. 3 (single-lane intersection, one SV, summed over its manoeuvres):
FIG3 = {"north": {"left": 2, "straight": 1, "right": 1},
        "west": {"left": 2, "straight": 2, "right": 1},
        "east": {"left": 2, "straight": 3, "right": 0}}


@pytest.mark.parametrize("arm", FIG3)
def test_fig3_potential_collision_points_from_geometry(arm):
    r = load_map("single_lane_4way")
    assert {t: r.pcp_count(t, arm) for t in TASKS} == FIG3[arm]


def test_pcp_per_manoeuvre_parts_add_up_and_reject_bad_input():
    r = load_map("single_lane_4way")
    for arm in FIG3:
        for t in TASKS:
            assert sum(r.pcp_count(t, arm, sv_maneuver=m) for m in TASKS) == r.pcp_count(t, arm)
    # opposing straight paths are parallel: no conflict point; crossing straights: exactly one
    assert r.pcp_count("straight", "north", sv_maneuver="straight") == 0
    assert r.pcp_count("straight", "west", sv_maneuver="straight") == 1
    with pytest.raises(ValueError, match="unknown task"):
        r.pcp_count("u-turn", "north")
    with pytest.raises(ValueError, match="SV arm"):
        r.pcp_count("left", "south")


# ----------------------------------------------------------------------------- map pose
def test_map_pose_places_the_junction_in_the_map_frame_and_back(tmp_path):
    """``pose`` moves the map's own frame (junction at its origin) into the fixed map frame:
    a state and a pose go there and back unchanged; the lane geometry itself is unchanged."""
    from bimacppo_sim.geometry import MapFrame

    plain = load_map("dual_lane_4way")
    moved = load_map(_write(tmp_path, pose={"x": 412.0, "y": -318.5, "heading": 0.6}))
    assert plain.frame.identity and not moved.frame.identity
    assert np.array_equal(moved.lanes["south_in_0"].points, plain.lanes["south_in_0"].points)
    f = moved.frame
    centre = f.poses_to_world(np.array([0.0, 0.0, 0.0]))
    assert np.allclose(centre, [412.0, -318.5, 0.6])
    # the south arm's in-lane heads north in the map's own frame: rotated by 0.6 rad in the map frame
    x, y, psi = plain.lane_point("south_in_0", 10.0)
    w = f.states_to_world(np.array([[x, y, 5.0, psi]]))[0]
    assert math.isclose(w[3], psi + 0.6, abs_tol=1e-12) and w[2] == 5.0
    assert math.hypot(w[0] - 412.0, w[1] + 318.5) == pytest.approx(math.hypot(x, y))
    back = f.states_to_map(w)
    assert np.allclose(back, [x, y, 5.0, psi], atol=1e-9)
    assert f.states_to_map(np.zeros((0, 4))).shape == (0, 4)
    assert MapFrame().states_to_world(np.array([1.0, 2.0, 3.0, 4.0])).tolist() == [1.0, 2.0, 3.0, 4.0]


@pytest.mark.parametrize("pose, msg", [({"x": 1e6}, "out of range"), ({"x": 1.0, "z": 2.0}, "key 'pose'"),
                                       ([1.0, 2.0], "key 'pose'"), ({"heading": 4.0}, "out of range")])
def test_bad_map_pose_is_refused(tmp_path, pose, msg):
    with pytest.raises(ValueError, match=msg):
        load_map(_write(tmp_path, pose=pose))


def test_n_pcp_inferred_from_what_a_receiver_sees_matches_the_world():
    """From the EV's start, the goal and each SV's first and last positions: the world's
    N_pcp whenever every SV was seen on its out-lane; never more than it otherwise."""
    from bimacppo_sim import Scenario, World

    road = load_map("dual_lane_4way")
    w = World(road)
    exact = lower = 0
    for seed in range(12):
        for task in TASKS:
            w.reset(Scenario(n_sv=3, task=task, seed=seed))
            ev0 = w.ego[:2].copy()
            tracks = {i: [s[:2].copy(), s[:2].copy()] for i, s in zip(w.sv_ids, w.sv_states())}
            for _ in range(300):
                done = w.step(np.array([1.0, 0.0])).done
                for i, s in zip(w.sv_ids, w.sv_states()):
                    tracks[i][1] = s[:2].copy()
                if done:
                    break
            n = road.infer_n_pcp(ev0, w.goal[:2], [tuple(t) for t in tracks.values()])
            left = all((loc := road.locate(*last)) is not None and road.lanes[loc[0]].kind == "out"
                       for _, last in tracks.values())
            if left:
                assert n == w.n_pcp, (task, seed)
                exact += 1
            else:
                assert n <= w.n_pcp, (task, seed)
                lower += 1
    assert exact >= 5, (exact, lower)
    assert road.infer_n_pcp(ev0, (0.0, 0.0), []) is None          # goal on no exit lane: no task
    assert load_map("three_lane_straight").infer_n_pcp((0.0, 0.0), (0.0, 10.0), []) == 0


@pytest.mark.parametrize("radius", [0.3, 1.6, 2.9])
def test_the_path_lookup_grid_is_the_nearest_point_over_the_whole_bounding_box(radius):
    """build_grid searches only the cells near the path; its grid must be what the search over
    every cell of the path's bounding box gives: the same cells, the nearest sample's arc length
    (the first one on a tie), for a curve that bends back on itself and a straight line."""
    from bimacppo_sim.geometry import Path, grid_key

    t = np.linspace(0.0, 1.0, 60)
    curves = [np.c_[20.0 * np.cos(4.0 * t), 12.0 * np.sin(4.0 * t) + 3.0 * t],
              np.c_[np.linspace(-7.3, 31.0, 40), np.full(40, 2.25)]]
    cell = 0.5
    for pts in curves:
        path = Path(pts, 0.25)
        path.build_grid(cell, radius)
        P = path.points()
        lo = np.floor((P.min(axis=0) - radius) / cell).astype(int)
        hi = np.floor((P.max(axis=0) + radius) / cell).astype(int)
        expected = {}
        for ix in range(lo[0], hi[0] + 1):
            cx = (ix + 0.5) * cell
            d = np.hypot(cx - P[:, 0][None, :], ((np.arange(lo[1], hi[1] + 1) + 0.5) * cell)[:, None] - P[:, 1][None, :])
            j = np.argmin(d, axis=1)
            for row, iy in enumerate(range(lo[1], hi[1] + 1)):
                if d[row, j[row]] <= radius:
                    expected[grid_key(ix, iy)] = j[row] * path.ds
        assert path.grid == expected
        assert path.lookup(*P[len(P) // 2]) == pytest.approx(len(P) // 2 * path.ds, abs=cell)
        assert path.lookup(P[0, 0] + 50.0, P[0, 1] + 50.0) is None
