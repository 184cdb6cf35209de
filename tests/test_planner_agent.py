"""The deployed HighLevelPlanner reproduces the training environment's decisions exactly."""
import numpy as np
import pytest

from bimacppo_planner.agent import HighLevelPlanner, load_policy, observed_goal, route_for
from bimacppo_sim import WorldConfig, load_map
from bimacppo_learning.checkpoint import CheckpointError, export_policy
from bimacppo_planner.decision import EnvConfig
from bimacppo_learning.env import IntersectionEnv
from bimacppo_learning.ppo import PPO


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory):
    cfg = EnvConfig.load()
    agent = PPO(cfg.obs_dim, cfg.nvec, seed=3)
    path = tmp_path_factory.mktemp("pol") / "policy.pt"
    export_policy(agent, path)
    return path


def test_planner_route_from_poses_equals_world_route():
    env = IntersectionEnv()
    for seed in range(6):
        env.reset(options={"n_sv": 1, "task": seed % 3, "scenario_seed": seed})
        w = env.world
        route = route_for(env.road, np.array([w.ego[0], w.ego[1], w.ego[3]]), w.goal)
        np.testing.assert_array_equal(route, w.route)


@pytest.mark.parametrize("map_id", ["dual_lane_4way", "single_lane_4way"])
def test_observed_goal_is_the_world_goal_over_whole_episodes(map_id):
    """Training observes the world's goal: the projection must be the identity on every
    goal and EV position our world produces, or deployment would observe otherwise."""
    env = IntersectionEnv(map_id=map_id)
    rng = np.random.default_rng(0)
    for seed in range(9):
        env.reset(options={"n_sv": 0, "task": seed % 3, "scenario_seed": seed})
        done = False
        while not done:
            w = env.world
            np.testing.assert_array_equal(observed_goal(env.road, w.goal, w.ego[:2]), w.goal)
            _, _, term, trunc, _ = env.step(env.action_space.sample() if rng.random() < 0.3
                                            else np.array([4, 2, 1]))
            done = term or trunc


def test_observed_goal_of_a_far_goal_sits_where_training_put_goals():
    road, cfg = load_map("dual_lane_4way"), WorldConfig.load()
    d, H = cfg.success_distance, road.H
    far = np.array([0.5 * road.lane_width, H + 25.0, np.pi / 2])     # straight, 25 m past the exit
    # approaching and inside the junction: success_distance past the exit, the source's heading
    np.testing.assert_allclose(observed_goal(road, far, (1.75, -40.0), cfg), [far[0], H + d, far[2]])
    np.testing.assert_allclose(observed_goal(road, far, (0.0, 0.0), cfg), [far[0], H + d, far[2]])
    # on the exit arm (either lane): success_distance ahead of the EV, never beyond the goal
    np.testing.assert_allclose(observed_goal(road, far, (5.25, H + 5.0), cfg), [far[0], H + 5.0 + d, far[2]])
    np.testing.assert_allclose(observed_goal(road, far, (1.75, H + 22.0), cfg), far)
    # a goal nearer than training's is observed at training's distance too
    near = np.array([far[0], H + 3.0, far[2]])
    np.testing.assert_allclose(observed_goal(road, near, (1.75, -40.0), cfg), [far[0], H + d, far[2]])
    # off the exit lanes, or on a straight road: as it is
    odd = np.array([1.75, -30.0, np.pi / 2])
    np.testing.assert_array_equal(observed_goal(road, odd, (1.75, -40.0), cfg), odd)
    g = np.array([0.0, 40.0, np.pi / 2])
    np.testing.assert_array_equal(observed_goal(load_map("three_lane_straight"), g, (0.0, 0.0), cfg), g)


def test_planner_observes_the_projected_goal(policy_file):
    road = load_map("dual_lane_4way")
    hp = HighLevelPlanner(load_policy(policy_file), road)
    ego = np.array([1.75, -50.0, 5.0, np.pi / 2])
    far = np.array([1.75, road.H + 25.0, np.pi / 2])
    hp.reset(ego, far)
    _, info = hp.step(ego, np.zeros((0, 4)))
    assert info["obs"][1] == pytest.approx(road.H + WorldConfig.load().success_distance + 50.0)
    assert hp.goal[1] == far[1]                       # the route and success still use the source's goal


def test_route_from_inside_the_junction_follows_the_episode_route():
    """A planner (re)started while the EV crosses the junction (no straight lane under it)
    still gets a route: the episode's own route from the nearest point on, same spacing."""
    env = IntersectionEnv()
    for seed in range(6):
        env.reset(options={"n_sv": 0, "task": seed % 3, "scenario_seed": seed})
        w = env.world
        inside = [p for p in w.route if env.road.locate(p[0], p[1]) is None]
        assert inside, "every intersection route crosses the junction box"
        for p in inside[:: max(1, len(inside) // 3)]:
            route = route_for(env.road, np.array(p), w.goal)
            assert np.hypot(*(route[0, :2] - p[:2])) < 0.5
            # the rest is the episode's route: same end, every waypoint on it (within 0.3 m)
            np.testing.assert_allclose(route[-1, :2], w.route[-1, :2], atol=0.5)
            d = np.hypot(route[:, None, 0] - w.route[None, :, 0], route[:, None, 1] - w.route[None, :, 1])
            assert d.min(axis=1).max() < 1.6   # waypoints interleave the 3 m spaced originals
            assert abs(len(route) - (len(w.route) - int(np.argmin(np.hypot(*(w.route[:, :2] - p[:2]).T))))) <= 1
    # the heading picks the connector: driving against it is not a route start
    p = inside[len(inside) // 2]
    with pytest.raises(ValueError, match="not on a straight lane"):
        route_for(env.road, np.array([p[0], p[1], p[2] + np.pi]), w.goal)


def test_route_for_a_late_start_in_a_lane_that_cannot_turn():
    """A planner that sees the episode late (restarted, or its goal delivered late) may find
    the EV still in the right lane for a left turn, inside the no-lane-change zone: it gets
    a route that changes lane late and ends at the goal, instead of "no route"."""
    env = IntersectionEnv()
    road = env.road
    for task, lane in ((0, "south_in_1"), (2, "south_in_0")):
        env.reset(options={"n_sv": 0, "task": task, "scenario_seed": 1})
        goal, full = env.world.goal, env.world.route
        length = road.lanes[lane].length
        for s in (length - road.cfg.no_lane_change_zone + 1.0, length - 0.1):
            x, y, psi = road.lane_point(lane, s)
            with pytest.raises(ValueError, match="no route"):   # the strict planner cannot
                road.plan_route(lane, s, road.locate(goal[0], goal[1])[0], 10.0)
            route = route_for(road, np.array([x, y, psi]), goal)
            np.testing.assert_allclose(route[0, :2], [x, y], atol=1e-9)
            assert np.hypot(*(route[:, :2] - goal[:2]).T).min() < 2.0   # passes the goal
            np.testing.assert_allclose(route[-1, :2], full[-1, :2], atol=3.5)  # and runs on past it
            assert np.all(np.hypot(*np.diff(route[:, :2], axis=0).T) < 4.0)     # no jumps


def test_planner_on_raw_states_matches_env_decisions(policy_file):
    env = IntersectionEnv()
    policy = load_policy(policy_file)
    hp = HighLevelPlanner(policy, env.road)
    for seed, task in ((1, "left"), (2, "straight")):
        obs, _ = env.reset(options={"n_sv": 3, "task": task, "scenario_seed": seed})
        hp.reset(env.world.ego, env.world.goal)   # route computed from poses, as the ROS node does
        for _ in range(60):
            x_imr, info = hp.step(env.world.ego, env.world.sv_states())
            np.testing.assert_array_equal(info["obs"], obs)
            action = policy.act(obs, deterministic=True)
            np.testing.assert_array_equal(info["action"], action)
            obs, _, term, trunc, einfo = env.step(action)
            np.testing.assert_array_equal(einfo["x_imr"], x_imr)
            if term or trunc:
                break


def test_planner_rejects_bad_input(policy_file, tmp_path):
    hp = HighLevelPlanner.load(policy_file)
    with pytest.raises(RuntimeError, match="before reset"):
        hp.step(np.zeros(4), np.zeros((0, 4)))
    with pytest.raises(ValueError, match="NaN"):
        hp.reset(np.array([0, -40, np.nan, 1.57]), np.array([0, 0, 0]))
    with pytest.raises(ValueError, match="not on a straight lane"):
        hp.reset(np.array([100.0, 100.0, 0.0, 0.0]), np.array([-23.0, 5.25, np.pi]))
    with pytest.raises(CheckpointError, match="no such file"):
        load_policy(tmp_path / "missing.pt")
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError):
        load_policy(bad)
    wrong = tmp_path / "wrong.pt"
    export_policy(PPO(10, (5, 5, 3), seed=0), wrong)
    with pytest.raises(CheckpointError, match="obs_dim"):
        HighLevelPlanner.load(wrong)


@pytest.mark.parametrize("variant, frm, rights", [("ev", "ev", 20), ("chosen", "chosen", 2), ("ev_idle_reach", "ev", 20),
                                                  ("ev_idle_lanes", "ev", 20)])
def test_planner_decodes_lane_changes_from_where_the_ev_drives_as_the_env_does(tmp_path, variant, frm, rights):
    """The three-lane road with A3 counted from the EV's lane or from the chosen lane (the latter
    state kept over the episode), and with A1's reach bounded by A2's speed: the planner, given
    the raw states and its own route, sends the env's x_IMR at every decision through the right
    changes (held for 6 s from the EV's lane; two decisions from the chosen lane) and the "keep"
    decisions that hold the far lane."""
    from conftest import REPO
    cfg = EnvConfig.load(REPO / f"studies/config/env_wait_chord_junction_road_overtake_{variant}.yaml")
    assert (cfg.action.reach_time is not None) == variant.endswith("reach")
    assert cfg.action.lane_change_from == frm
    path = tmp_path / "policy.pt"
    export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=3), path)
    env = IntersectionEnv("three_lane_straight", config=cfg)
    hp = HighLevelPlanner(load_policy(path), env.road, config=cfg)
    script = [np.array([4, 3, 2])] * rights + [np.array([4, 3, 1])] * (30 - rights)
    hp._act = lambda obs: script[len(seen)]
    seed = next(s for s in range(100) if env.reset(options={"n_sv": 0, "task": "straight", "scenario_seed": s})
                and env.world.start_lane == "road_0")
    obs, _ = env.reset(options={"n_sv": 0, "task": "straight", "scenario_seed": seed})
    if cfg.observation.lanes:                   # the lane features: the leftmost lane, two to its right
        assert list(obs[-2:]) == [0.0, 2.0]
    hp.reset(env.world.ego, env.world.goal)
    seen = []
    for action in script:
        x_imr, info = hp.step(env.world.ego, env.world.sv_states())
        np.testing.assert_array_equal(info["obs"], obs)
        seen.append(info["lane_change"])
        obs, _, term, trunc, einfo = env.step(action)
        np.testing.assert_array_equal(einfo["x_imr"], x_imr)
        assert einfo["lane_change"] == info["lane_change"] and not (term or trunc)
    lanes_over = (env.world.ego[0] - env.road.lane_point("road_0", 0.0)[0]) / env.road.lane_width
    # the bounded reach aims at most 18 deg off the road at 6 m/s, so it is still settling there
    assert abs(lanes_over - 2.0) < (0.3 if cfg.action.reach_time else 0.15) and seen[0] and not any(seen[rights:])
    if frm == "chosen":
        assert all(seen[:rights])
    if cfg.observation.lanes:                   # ... and two lanes over, the rightmost lane
        assert list(obs[-2:]) == [2.0, 0.0]


@pytest.mark.parametrize("name, lane_change_from, leads", [("bimacppo_three_lane_overtake_continued.pt", "chosen", True),
                                                           ("bimacppo_three_lane_overtake_leads.pt", "chosen", True),
                                                           ("bimacppo_three_lane_overtake_ev.pt", "ev", False)])
def test_the_overtaking_policy_runs_on_the_three_lane_road_as_evaluated(name, lane_change_from, leads):
    """studies/policies' overtaking fine-tunes record their decoding (lane changes from the
    chosen lane or the EV's), their observation (the lead features or not) and median actions:
    the deployed planner built from the file alone observes what the env observes and sends the
    env's x_IMR at every decision of a scenario with two slow SVs."""
    from conftest import REPO
    from bimacppo_learning.evaluate import eval_seed
    path = REPO / "studies/policies" / name
    hp = HighLevelPlanner.load(path, map_id="three_lane_straight")
    assert hp.cfg.action.lane_change_from == lane_change_from and hp.action_selection == "median"
    assert hp.cfg.observation.leads is leads
    env = IntersectionEnv("three_lane_straight", config=hp.cfg)
    obs, _ = env.reset(options={"n_sv": 3, "task": "straight", "scenario_seed": eval_seed(1, 3, 0, "validation"),
                                "n_slow": 2})
    hp.reset(env.world.ego, env.world.goal)
    for _ in range(40):
        x_imr, info = hp.step(env.world.ego, env.world.sv_states())
        np.testing.assert_array_equal(info["obs"], obs)
        obs, _, term, trunc, einfo = env.step(info["action"])
        np.testing.assert_array_equal(einfo["x_imr"], x_imr)
        if term or trunc:
            break
