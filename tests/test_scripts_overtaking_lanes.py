"""scripts/overtaking_lanes.py: the lane distance the overtaking scenarios ask for."""
import pytest
from conftest import load_script


def test_without_slow_svs_every_lane_is_free_and_two_slow_svs_sometimes_block_two_lanes(capsys):
    script = load_script("overtaking_lanes")
    none = script.distances("validation", 30, slow_max=0)
    assert none == {0: 30}
    two = script.distances("validation", 100, slow_max=2)
    assert sum(two.values()) == 100 and set(two) <= {0, 1, 2} and two[2] > 0 and two[1] > 0
    assert script.main(["--seed-set", "validation", "--episodes", "100"]) == 0
    out = capsys.readouterr().out
    assert f"  2: {two[2]} scenarios" in out


def test_bad_arguments_end_in_a_usage_error(capsys):
    script = load_script("overtaking_lanes")
    for argv in (["--episodes", "0"], ["--slow-svs", "4"]):
        try:
            script.main(argv)
        except SystemExit as exc:
            assert exc.code == 2
        else:
            raise AssertionError(f"{argv} accepted")
        assert "error:" in capsys.readouterr().err


def test_a_policys_outcomes_split_by_distance_add_up_to_its_evaluation(tmp_path, capsys):
    """The same scenarios as bimacppo-evaluate's overtaking protocol: per-distance outcomes of a
    constant "keep the lane at 8 m/s" driver sum to what the evaluator counts on the same seeds."""
    from collections import Counter

    import numpy as np
    from bimacppo_learning.evaluate import evaluate
    from bimacppo_planner.decision import EnvConfig

    class KeepLane:
        def act(self, obs):
            return np.array([4, 4, 1])
    script = load_script("overtaking_lanes")
    n = 12
    by = script.outcomes_by_distance(KeepLane(), "validation", n)
    assert {d: sum(c.values()) for d, c in by.items()} == dict(script.distances("validation", n))
    cell = evaluate(KeepLane(), map_id="three_lane_straight", n_svs=(3,), tasks=(1,), episodes=n, workers=1,
                    random_row=False, seed_set="validation", slow_svs=2,
                    env_config=EnvConfig.load())[0]
    total = sum(by.values(), Counter())
    assert total["success"] == cell.counts.get("success", 0)
    assert total["timeout"] == cell.counts.get("timeout", 0)
    assert total["sv collision"] + total["off road"] == cell.counts.get("collision", 0)



def test_the_scripted_probe_passes_slow_svs_where_its_lane_is_blocked():
    """scripts/overtaking_probe.py: on the first 20 validation scenarios it succeeds in at least 18,
    among them at least 6 of the 7 that need one or two lane changes (the decoding lets a driver
    pass), choosing A1 by its speed or leaving that to action.reach_time; outcomes add up. (Single
    scenarios are knife-edge: a change of the NMPC's plans at the level of its stopping tolerance
    moves a discrete decision a tick and can flip one outcome, so no single one is required.)"""
    probe = load_script("overtaking_probe")
    for reach_time in (None, 1.5):
        by = probe.run("validation", 20, reach_time=reach_time)
        assert sum(sum(c.values()) for c in by.values()) == 20
        assert sum(c["success"] for c in by.values()) >= 18, (reach_time, by)
        assert sum(sum(c.values()) for d, c in by.items() if d >= 1) == 7
        assert sum(c["success"] for d, c in by.items() if d >= 1) >= 6, (reach_time, by)


@pytest.mark.parametrize("bad", ["0", "-1", "nan"])
def test_the_probe_refuses_a_reach_time_that_is_not_a_positive_number(bad, capsys):
    probe = load_script("overtaking_probe")
    with pytest.raises(SystemExit) as e:
        probe.main(["--reach-time", bad, "--episodes", "1"])
    assert e.value.code == 2 and "--reach-time must be a positive number" in capsys.readouterr().err


def test_per_scenario_records_count_a3_asks_for_a_lane_that_is_not_there(capsys):
    """A driver that always asks A3 for the left lane asks for a missing one at every decision it
    drives in the leftmost lane and at none in the others; the records add up to the outcomes,
    and the start lane is 'edge' exactly where one side has no lane."""
    import numpy as np
    from bimacppo_learning.env import IntersectionEnv
    from bimacppo_planner.decision import EnvConfig

    script = load_script("overtaking_lanes")
    env = IntersectionEnv(map_id=script.MAP, config=EnvConfig.load(overrides={"action": {"lane_change_from": "ev"}}))
    seen = {"left": 0, "other": 0}

    def always_left(env, obs):
        x, y, _, psi = env.world.ego_tuple()
        seen["left" if script.lanes_beside(env.world.road, x, y, psi)[0] == 0 else "other"] += 1
        return np.array([2, 3, 0])
    records: list = []
    try:
        by = script.run_by_distance(env, always_left, "validation", 8, episodes_out=records)
    finally:
        env.close()
    assert len(records) == 8 and sum(sum(c.values()) for c in by.values()) == 8
    assert sum(r["a3_no_lane"] for r in records) == seen["left"] > 0 and seen["other"] > 0
    assert {r["outcome"] for r in records} <= set(script.CAUSES)
    table = script.by_start_lane_markdown(records)
    assert table.count("\n") >= 2 and ("edge" in table or "middle" in table)


def test_collision_kind_tells_rear_end_collisions_from_the_rest():
    """Ahead of the EV within half a lane of its heading line is a rear-end collision, split by
    whether the SV is slow; beside or behind is the rest."""
    import math

    from bimacppo_sim import Scenario, World, load_map

    script = load_script("overtaking_lanes")
    w = World(load_map(script.MAP))
    w.reset(Scenario(n_sv=3, task="straight", seed=2, n_slow=1))
    w._ev[:] = [0.0, 0.0, 5.0, math.pi / 2]
    sv = w.svs[0]
    half = 0.5 * w.road.lane_width
    for x, y, slow, kind in ((0.3 * half, 4.0, True, script.KINDS[0]), (-0.3 * half, 4.0, False, script.KINDS[1]),
                             (1.2 * half, 4.0, True, script.KINDS[2]), (0.0, -4.0, True, script.KINDS[2])):
        sv.x, sv.y, sv.slow = x, y, slow
        assert script.collision_kind(w, sv.id) == kind, (x, y, slow)


def test_a_lane_keeper_rear_ends_the_slow_svs_that_block_its_lane():
    """A driver that keeps its lane at 8 m/s: every collision with an SV is recorded with its kind
    and the EV's speed, at least one is a rear-end collision with a slow SV, and the table lists
    each distance."""
    import numpy as np
    from bimacppo_learning.env import IntersectionEnv
    from bimacppo_planner.decision import EnvConfig

    script = load_script("overtaking_lanes")
    env = IntersectionEnv(map_id=script.MAP, config=EnvConfig.load())
    records: list = []
    try:
        script.run_by_distance(env, lambda env, obs: np.array([4, 4, 1]), "validation", 12, episodes_out=records)
    finally:
        env.close()
    hits = [r for r in records if r["outcome"] == "sv collision"]
    assert hits and all(r["kind"] in script.KINDS and r["ev_speed"] >= 0.0 for r in hits)
    assert all("kind" not in r for r in records if r["outcome"] != "sv collision")
    assert any(r["kind"] == script.KINDS[0] for r in hits)
    table = script.collisions_markdown(records)
    assert len(table.splitlines()) == 2 + len({r["distance"] for r in records})


def test_the_probe_can_decide_one_part_of_a_policys_actions(capsys):
    """--policy with --probe-heads: a driver that keeps its lane at 8 m/s rear-ends slow SVs on its
    own; with the probe's A3 it changes lanes and does better where its lane is blocked, with the
    probe's A1 and A2 it stops behind them instead (no collision where it starts blocked). Outcomes
    add up; a policy that does not decode from the chosen lane, and half the pair, are refused."""
    import numpy as np
    from bimacppo_planner.decision import EnvConfig

    probe = load_script("overtaking_probe")
    cfg = EnvConfig.load(probe.CONFIG)

    class KeepLane:
        def act(self, obs):
            return np.array([4, 4, 1])
    n = 12
    alone = load_script("overtaking_lanes").run_by_distance(
        probe.IntersectionEnv(probe.MAP, config=cfg), lambda env, obs: np.array([4, 4, 1]), "validation", n)
    lane = probe.run_with_policy(KeepLane(), "lane", "validation", n, env_config=cfg)
    speed = probe.run_with_policy(KeepLane(), "speed", "validation", n, env_config=cfg)
    for by in (alone, lane, speed):
        assert sum(sum(c.values()) for c in by.values()) == n

    def blocked_ok(by):
        return sum(c["success"] for d, c in by.items() if d >= 1)
    assert blocked_ok(alone) == 0 < blocked_ok(lane)
    assert sum(c["sv collision"] for d, c in speed.items() if d >= 1) == 0
    with pytest.raises(SystemExit) as e:
        probe.main(["--policy", "x.pt"])
    assert e.value.code == 2 and "go together" in capsys.readouterr().err
    ev = EnvConfig.load(overrides={"action": {"lane_change_from": "ev"}})
    with pytest.raises(ValueError, match="KeepLane: decodes lane changes from the 'ev' lane"):
        probe.run_with_policy(KeepLane(), "lane", "validation", 1, env_config=ev)


def test_the_headway_test_is_counted_per_scenario_and_flags_a_rear_end_collision_before_it():
    """Keeping the lane at 8 m/s rear-ends the slow SVs of the scenarios whose own lane is
    blocked: each such collision had a decision that began closing on the lead too fast to stop
    (``closing_on_lead``) at least one decision before it; the per-outcome table counts every
    scenario once."""
    import numpy as np

    class KeepLane:
        def act(self, obs):
            return np.array([4, 4, 1])
    script = load_script("overtaking_lanes")
    records: list = []
    script.outcomes_by_distance(KeepLane(), "validation", 12, episodes_out=records)
    rear = [r for r in records if r.get("kind") == "rear-end, slow SV"]
    assert rear, [r["outcome"] for r in records]
    assert all(r["closing"] > 0 and r["first_closing_before_end"] >= 1 for r in rear)
    assert all((r["closing"] == 0) == (r["first_closing_before_end"] is None) for r in records)
    table = script.closing_markdown(records)
    counted = sum(int(line.split("|")[2]) for line in table.splitlines()[2:])
    assert counted == len(records)


def test_lane_change_reversals_are_counted_and_the_commitment_removes_most_of_them():
    """A driver that asks right and left in turn at 4 m/s, lane changes counted from the chosen
    lane: without the commitment every scenario that lasts a few decisions reverses a lane change
    within the window; with it (action.lane_change_commit) a change is driven before the next one
    counts, so far fewer changes are reversed. Keeping the lane reverses none. Each table counts
    every scenario once."""
    import numpy as np
    from bimacppo_planner.decision import EnvConfig

    class Weave:
        def __init__(self):
            self.k = 0

        def act(self, obs):
            self.k += 1
            return np.array([4, 2, 2 if self.k % 2 else 0])

    class KeepLane:
        def act(self, obs):
            return np.array([4, 2, 1])
    script = load_script("overtaking_lanes")
    n, counts = 6, {}
    for name, driver, commit in (("keep", KeepLane(), None), ("weave", Weave(), None), ("commit", Weave(), 1.0)):
        cfg = EnvConfig.load(overrides={"action": {"lane_change_from": "chosen", "lane_change_commit": commit}})
        env, act = script.policy_driver(driver, env_config=cfg)
        records: list = []
        try:
            script.run_by_distance(env, act, "validation", n, episodes_out=records)
        finally:
            env.close()
        counts[name] = [r["reversals"] for r in records]
        table = script.reversals_markdown(records)
        assert sum(int(line.split("|")[2]) for line in table.splitlines()[2:]) == n
    assert counts["keep"] == [0] * n
    assert all(r >= 1 for r in counts["weave"]), counts
    assert sum(counts["commit"]) < sum(counts["weave"]) / 3, counts


def test_a_policy_runs_in_another_env_config_and_a_mismatch_is_one_usage_error(tmp_path, capsys):
    """--env-config runs the policy under another decoding (the lane-change commitment here); an
    env config whose observation the policy does not take, or a broken file, ends in one
    ``error:`` line with exit code 2."""
    from conftest import REPO
    script = load_script("overtaking_lanes")
    policy = str(REPO / "studies/policies/bimacppo_three_lane_overtake_leads.pt")
    commit = str(REPO / "studies/config/env_wait_chord_junction_road_overtake_chosen_queue_leads_commit.yaml")
    assert script.main([policy, "--episodes", "2", "--env-config", commit]) == 0
    assert "lane-change reversals" in capsys.readouterr().out
    broken = tmp_path / "broken.yaml"
    broken.write_text("action: [unclosed\n")
    for cfg in (str(REPO / "bimacppo_planner/bimacppo_planner/config/env.yaml"), str(broken)):
        with pytest.raises(SystemExit) as e:
            script.main([policy, "--episodes", "2", "--env-config", cfg])
        err = capsys.readouterr().err
        assert e.value.code == 2 and "error:" in err and "Traceback" not in err, err


def test_records_name_each_scenario_and_are_never_overwritten(tmp_path, capsys):
    """--records writes one JSON line per scenario, in order, with its scenario seed and outcome
    as the tables count them (policy and probe alike); an existing file or a missing folder is one
    usage error and nothing is run."""
    import json

    from conftest import REPO
    from bimacppo_learning.evaluate import eval_seed
    script, probe = load_script("overtaking_lanes"), load_script("overtaking_probe")
    policy = str(REPO / "studies/policies/bimacppo_three_lane_overtake_leads.pt")
    out = tmp_path / "p.jsonl"
    assert script.main([policy, "--episodes", "3", "--records", str(out)]) == 0
    table = capsys.readouterr().out
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    assert [r["scenario_seed"] for r in recs] == [eval_seed(1, 3, k, "validation") for k in range(3)]
    assert f"| all | 3 | {sum(r['outcome'] == 'success' for r in recs)} |" in table
    assert probe.main(["--episodes", "2", "--seed-set", "test", "--records", str(tmp_path / "q.jsonl")]) == 0
    capsys.readouterr()
    q = [json.loads(line) for line in (tmp_path / "q.jsonl").read_text().splitlines()]
    assert [r["scenario_seed"] for r in q] == [eval_seed(1, 3, k, "test") for k in range(2)]
    before = out.read_text()
    for argv, mod in (([policy, "--episodes", "1", "--records", str(out)], script),
                      ([policy, "--episodes", "1", "--records", str(tmp_path / "no" / "r.jsonl")], script),
                      (["--episodes", "1", "--records", str(out)], probe),
                      (["--episodes", "1", "--records", str(tmp_path / "none.jsonl")], script)):
        with pytest.raises(SystemExit) as e:
            mod.main(argv)
        err = capsys.readouterr().err
        assert e.value.code == 2 and "--records" in err and "Traceback" not in err
    assert out.read_text() == before
