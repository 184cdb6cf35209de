"""The scripted drivers' threat test and junction distance: the event the threat-entry shaping
term pays on must separate the "yield" rule (enters only a clear junction) from "go"."""
import math

import pytest
from bimacppo_sim import Scenario, World, load_map
from bimacppo_sim.config import DriverConfig
from bimacppo_sim.drivers import (closing_on_lead, junction_distance, junction_threatened, lanes_to_free_lane, lead_vehicle,
                                  make_driver, queued_behind_lead, stop_line_distance)


def _threatened_entries(driver: str, episodes: int) -> tuple[int, int]:
    road = load_map("dual_lane_4way")
    w, cfg = World(road), DriverConfig.load()
    entered = threatened = 0
    for k in range(episodes):
        w.reset(Scenario(n_sv=3, task=("left", "straight", "right")[k % 3], seed=7000 + k))
        drv = make_driver(driver, w)
        inside = False
        while True:
            before = junction_threatened(w, cfg)
            res = w.step(drv.act())
            if not inside and junction_distance(w) <= 0.0:
                inside, entered, threatened = True, entered + 1, threatened + int(before)
            if res.done:
                break
    return entered, threatened


def test_yield_enters_only_clear_junctions_and_go_enters_threatened_ones():
    assert _threatened_entries("yield", 6) == (6, 0)
    entered, threatened = _threatened_entries("go", 6)
    assert entered >= 4 and threatened == entered


def test_stop_line_lies_stop_margin_before_the_box_and_no_junction_means_infinity():
    road = load_map("dual_lane_4way")
    w, cfg = World(road), DriverConfig.load()
    w.reset(Scenario(n_sv=0, task="left", seed=1))
    assert junction_distance(w) > 0.0
    assert stop_line_distance(w, cfg) == junction_distance(w) - cfg.stop_margin
    straight = World(load_map("three_lane_straight"))
    straight.reset(Scenario(n_sv=0, task="straight", seed=1))
    assert junction_distance(straight) == float("inf") and not junction_threatened(straight, cfg)


def test_time_to_box_is_zero_inside_infinite_when_leaving_and_gap_over_speed_otherwise():
    import math
    road = load_map("dual_lane_4way")
    H = road.H
    assert road.box_gap(0.0, -H - 7.0) == 7.0 and road.box_gap(1.0, 1.0) < 0.0
    assert road.time_to_box(1.0, -1.0, 5.0, 0.0) == 0.0                       # inside
    assert road.time_to_box(0.0, -H - 10.0, 5.0, math.pi / 2) == 2.0          # heading for the centre
    assert road.time_to_box(0.0, -H - 10.0, 5.0, -math.pi / 2) == math.inf    # heading away
    assert road.time_to_box(0.0, -H - 1.0, 0.0, math.pi / 2) == 1.0 / road.BOX_SPEED_FLOOR
    straight = load_map("three_lane_straight")
    assert straight.box_gap(0.0, 0.0) == math.inf and straight.time_to_box(0.0, 0.0, 5.0, 0.0) == math.inf


def test_lanes_to_free_lane_counts_to_the_nearest_lane_no_slow_sv_blocks_ahead():
    """Three-lane road, EV in lane 0: the count is 0 while its lane is free, and otherwise the lanes
    to the nearest one with no SV slower than slow_speed ahead within reach; an SV behind, too
    far ahead or fast blocks nothing; every lane blocked, or the EV inside a junction, gives None."""
    road = load_map("three_lane_straight")
    w = World(road)
    w.reset(Scenario(n_sv=3, task="straight", seed=3))
    w._ev[:] = [*road.lane_point("road_0", 20.0)[:2], 6.0, road.lane_point("road_0", 20.0)[2]]

    def count(*svs):     # (lane, metres ahead of the EV, speed) per SV; the rest inactive
        for sv in w.svs:
            sv.active = False
        for sv, (lane, ahead, v) in zip(w.svs, svs):
            sv.x, sv.y, sv.psi = road.lane_point(f"road_{lane}", 20.0 + ahead)
            sv.v, sv.active = v, True
        return lanes_to_free_lane(w, 4.0, 60.0)

    assert count() == 0 and count((1, 10.0, 1.0)) == 0
    assert count((0, 10.0, 1.0)) == 1 and count((0, 10.0, 1.0), (1, 30.0, 2.0)) == 2
    assert count((0, 10.0, 7.0)) == 0 and count((0, -10.0, 1.0)) == 0 and count((0, 70.0, 1.0)) == 0
    assert count((0, 10.0, 1.0), (1, 30.0, 2.0), (2, 50.0, 0.5)) is None
    junction = World(load_map("dual_lane_4way"))
    junction.reset(Scenario(n_sv=0, task="straight", seed=1))
    junction._ev[:2] = [0.0, 0.0]
    assert lanes_to_free_lane(junction, 4.0, 60.0) is None


def test_queued_behind_lead_tests_the_bumper_gap_to_the_sv_ahead_in_the_lane():
    """The gap is bumper to bumper (centre distance less one car length), to the nearest active
    SV ahead within half a lane of the EV's heading line, whatever the speeds; ``lead_vehicle``
    reports that gap and the lead's speed along the EV's heading, or None."""
    road = load_map("three_lane_straight")
    w = World(road)
    w.reset(Scenario(n_sv=2, task="straight", seed=3))
    near, far = w.svs[0], w.svs[1]
    length = w.cfg.vehicle.length
    w._ev[:] = [0.0, 0.0, 0.0, math.pi / 2]
    far.x, far.y, far.v, far.psi, far.active = 0.0, 50.0, 5.0, math.pi / 2, True

    def place(ahead, v_lead=1.0, side=0.0, active=True, psi=math.pi / 2):
        near.x, near.y, near.v, near.psi, near.active = side, ahead, v_lead, psi, active
        return queued_behind_lead(w, 20.0)

    assert place(20.0 + length - 0.1) and not place(20.0 + length + 0.1)
    assert place(8.0, v_lead=9.0)                                   # speed does not matter
    assert not place(8.0, side=road.lane_width)                     # one lane over
    assert not place(-8.0)                                          # behind
    assert not place(8.0, active=False)
    place(8.0, v_lead=2.0, psi=math.pi / 2 + math.pi / 3)           # heading 60 degrees off the EV's
    gap, v_along = lead_vehicle(w)
    assert gap == pytest.approx(8.0 - length) and v_along == pytest.approx(1.0)
    far.active = False
    place(8.0, active=False)
    assert lead_vehicle(w) is None


def test_closing_on_lead_tests_the_stop_behind_the_sv_ahead_in_the_lane():
    """v^2 - v_lead^2 > 2 b (gap - margin), gap bumper to bumper, for the nearest SV ahead within
    half a lane of the EV's heading line; nothing for an SV beside, behind, faster or inactive."""
    road = load_map("three_lane_straight")
    w, cfg = World(road), DriverConfig.load()
    w.reset(Scenario(n_sv=1, task="straight", seed=3))
    sv = w.svs[0]
    length, b, margin = w.cfg.vehicle.length, cfg.stop_decel, cfg.stop_margin

    def place(v, ahead, v_lead, side=0.0, active=True):
        w._ev[:] = [0.0, 0.0, v, math.pi / 2]
        sv.x, sv.y, sv.v, sv.psi, sv.active = side, ahead, v_lead, math.pi / 2, active
        return closing_on_lead(w, cfg)

    v, v_lead = 8.0, 2.0
    stop_gap = (v * v - v_lead * v_lead) / (2.0 * b) + margin + length   # centre distance of the boundary
    assert place(v, stop_gap - 0.1, v_lead) and not place(v, stop_gap + 0.1, v_lead)
    assert not place(v, 6.0, 9.0)                                  # the lead is faster
    assert not place(v, 6.0, v_lead, side=road.lane_width)          # one lane over
    assert place(v, 6.0, v_lead, side=0.4 * road.lane_width)        # within half a lane
    assert not place(v, -6.0, v_lead)                               # behind
    assert not place(v, 6.0, v_lead, active=False)
    assert not place(0.0, 6.0, 0.0)                                 # standing behind a standing SV
