"""The env's n_slow option and the overtaking wrapper the fine-tune relies on."""
import pytest

from bimacppo_learning import experiments as ex


# --- n_slow: the env option and the overtaking wrapper ------------------------------------


@pytest.fixture(scope="module")
def lane_env():
    from bimacppo_learning.env import IntersectionEnv

    return IntersectionEnv(map_id="three_lane_straight")


def _n_slow(env):
    return sum(sv.slow for sv in env.unwrapped.world.svs)


def test_env_n_slow_option(lane_env):
    lane_env.reset(options={"n_sv": 3, "task": "straight", "scenario_seed": 5, "n_slow": 2})
    assert _n_slow(lane_env) == 2
    lane_env.reset(options={"n_sv": 3, "task": "straight", "scenario_seed": 5})
    assert _n_slow(lane_env) == 0                      # absent: the Scenario default, no slow SV
    for bad in (4, -1, True, 1.5):
        with pytest.raises(ValueError, match="n_slow"):
            lane_env.scenario_from_options({"n_sv": 3, "task": "straight", "n_slow": bad})
    sc = lane_env.scenario_from_options({"n_sv": 3, "task": "straight", "n_slow": None})
    assert sc.n_slow is None


def test_overtake_env_folds_the_task_and_draws_n_slow_from_the_scenario_seed():
    env = ex.make_overtake_env("three_lane_straight", None, "fast", 2)()
    seen = set()
    for seed in range(30):
        env.reset(seed=seed, options={"n_sv": 3, "task": 0})
        assert env.scenario.task == "straight"
        k = _n_slow(env)
        assert k == env.scenario.n_slow == ex.draw_n_slow(env.scenario.seed, 3, 2)
        seen.add(k)
    assert seen == {0, 1, 2}
    env.reset(seed=3, options={"n_sv": 1, "task": 2})
    assert _n_slow(env) <= 1
    # explicit n_slow in the options wins (the fixed-seed overtaking tests set it)
    env.reset(options={"n_sv": 3, "task": "straight", "scenario_seed": 8, "n_slow": 0})
    assert _n_slow(env) == 0
    assert all(ex.draw_n_slow(s, 3, 2) == ex.draw_n_slow(s, 3, 2) for s in range(10))
    assert {ex.draw_n_slow(s, 3, 2) for s in range(200)} == {0, 1, 2}
    assert {ex.draw_n_slow(s, 1, 2) for s in range(200)} == {0, 1}
