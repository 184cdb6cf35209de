"""Surrounding vehicles: conflict resolution among themselves, difficulty for the EV."""
from collections import Counter

import pytest

from bimacppo_common.conventions import TASKS
from bimacppo_sim import Scenario, World, load_map, run_episode


@pytest.mark.parametrize("mid", ["dual_lane_4way", "single_lane_4way"])
def test_svs_alone_rarely_collide_and_never_deadlock(mid):
    w = World(load_map(mid))
    collided, unfinished = 0, 0
    for seed in range(1000):
        r = run_episode(w, Scenario(3, TASKS[seed % 3], seed, ev_present=False))
        collided += r.sv_collisions > 0
        unfinished += r.outcome != "success"
    assert collided < 10           # < 1 % of 1,000 episodes
    assert unfinished < 10         # all SVs leave the map (no deadlock)


def _rates(driver, task, n_sv, episodes, seed0=10000):  # the reference-table seeds
    w = World(load_map("dual_lane_4way"))
    c = Counter(run_episode(w, Scenario(n_sv, task, seed0 + e), driver).outcome for e in range(episodes))
    return {k: c[k] / episodes for k in ("success", "collision", "timeout")}


@pytest.mark.parametrize("task", ["left", "straight"])
def test_go_driver_collides_often_with_three_svs(task):
    assert _rates("go", task, 3, 100)["collision"] >= 0.40


def test_go_driver_is_safe_without_svs_and_svs_react_to_the_ev():
    assert _rates("go", "straight", 0, 20)["collision"] == 0.0


@pytest.mark.parametrize("task", TASKS)
def test_yield_driver_is_much_safer_than_go(task):
    y = _rates("yield", task, 3, 60)
    g = _rates("go", task, 3, 60)
    assert y["collision"] <= 0.05
    assert y["collision"] < g["collision"] or g["collision"] == 0.0


def test_styles_differ_in_yielding_to_a_stopped_ev_in_the_junction():
    # EV stops in the middle of the junction: conservative/moderate SVs crossing its
    # path stop; aggressive ones do not brake for a crossing EV and hit it more often
    w = World(load_map("dual_lane_4way"))
    hits = Counter()
    seen = Counter()
    for seed in range(120):
        w.reset(Scenario(1, "straight", seed))
        sv = w.svs[0]
        if w.road.connector_conflicts(w.ev_connector, sv.route.connector) == 0:
            continue
        seen[sv.style] += 1
        while True:
            x, y, v, psi = w.ego
            r = w.step([3.0 if y < -1 else -6.0, 0.0])
            if r.done:
                break
        hits[sv.style] += r.outcome == "collision"
    rate = {k: hits[k] / seen[k] for k in seen if seen[k]}
    assert rate["aggressive"] > rate["conservative"]
