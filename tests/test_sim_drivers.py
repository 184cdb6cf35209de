"""The scripted drivers' threat test and junction distance: the event the threat-entry shaping
term pays on must separate the "yield" rule (enters only a clear junction) from "go"."""
from bimacppo_sim import Scenario, World, load_map
from bimacppo_sim.config import DriverConfig
from bimacppo_sim.drivers import junction_distance, junction_threatened, make_driver, stop_line_distance


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
