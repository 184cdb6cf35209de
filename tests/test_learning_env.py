"""The high-level Gymnasium environment: API conformance, curriculum control, reward, determinism."""
import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from bimacppo_learning.env import MAP_IDS, IntersectionEnv, register_envs


@pytest.fixture(scope="module")
def env():
    e = IntersectionEnv(render_mode="rgb_array")
    yield e
    e.close()


def _rollout(env, options, policy, max_steps=400):
    obs, info = env.reset(options=options)
    traj = [env.world.ego.copy()]
    for _ in range(max_steps):
        obs, r, term, trunc, info = env.step(policy(obs))
        traj.append(env.world.ego.copy())
        assert np.all(np.isfinite(obs)) and np.isfinite(r)
        if term or trunc:
            return info, np.array(traj)
    raise AssertionError("episode did not end within the time limit")


def test_passes_gymnasium_env_checker(env):
    check_env(env, skip_render_check=True)


def test_registered_ids_make_envs():
    register_envs()
    for env_id in MAP_IDS:
        assert env_id in gym.registry
    e = gym.make("bimacppo/SingleLaneIntersection-v0")
    obs, _ = e.reset(seed=1, options={"n_sv": 2, "task": "left"})
    assert e.observation_space.contains(obs)
    e.close()


def test_reset_options_set_the_scenario(env):
    for n_sv in range(4):
        for task in range(3):
            obs, info = env.reset(options={"n_sv": n_sv, "task": task, "scenario_seed": 5})
            assert info["n_sv"] == n_sv and info["task"] == task
            assert len(env.world.sv_ids) == n_sv
            # padded SV slots after the real ones look like "nothing there"
            for k in range(n_sv, 3):
                np.testing.assert_allclose(obs[4 + 4 * k: 8 + 4 * k], [7.5, 7.5, 0, 0])
    with pytest.raises(ValueError, match="n_sv"):
        env.reset(options={"n_sv": 4})
    with pytest.raises(ValueError, match="task"):
        env.reset(options={"task": "u-turn"})
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(options={"nsv": 1})


def test_same_scenario_and_actions_give_the_same_trajectory(env):
    policy = lambda obs: np.array([3, 3, 1])  # noqa: E731
    opts = {"n_sv": 3, "task": "straight", "scenario_seed": 11}
    info1, t1 = _rollout(env, opts, policy)
    info2, t2 = _rollout(env, opts, policy)
    assert info1["outcome"] == info2["outcome"]
    np.testing.assert_array_equal(t1, t2)


def test_stopping_policy_times_out_and_far_waypoint_policy_moves(env):
    stop = lambda obs: np.array([0, 0, 1])  # noqa: E731 - WP0 at 0 m/s: the yield action
    info, traj = _rollout(env, {"n_sv": 0, "task": "right", "scenario_seed": 3}, stop)
    assert info["outcome"] == "timeout"
    assert np.linalg.norm(traj[-1, :2] - traj[0, :2]) < 15.0
    go = lambda obs: np.array([3, 3, 1])  # noqa: E731 - a far waypoint at 6 m/s
    info, traj = _rollout(env, {"n_sv": 0, "task": "straight", "scenario_seed": 3}, go)
    assert info["outcome"] == "success", info
    assert info["episode_return"] > 0


def test_success_reward_grows_with_difficulty(env):
    """eq. (28): r_S = r_S0 + alpha1*N_sv + alpha2*N_pcp; check the terminal reward on a success."""
    go = np.array([3, 3, 1])
    rc = env.cfg.reward
    for opts in ({"n_sv": 0, "task": "straight", "scenario_seed": 3},
                 {"n_sv": 0, "task": "left", "scenario_seed": 4}):
        env.reset(options=opts)
        while True:
            _, r, term, trunc, info = env.step(go)
            if term or trunc:
                break
        assert info["outcome"] == "success"
        expected = rc.success_base + rc.alpha1 * info["n_sv"] + rc.alpha2 * info["n_pcp"] + rc.step
        assert r == pytest.approx(expected)


def test_render_shows_the_scene(env):
    env.reset(options={"n_sv": 2, "task": "left", "scenario_seed": 1})
    env.step(np.array([2, 2, 0]))
    img = env.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8
    assert img.std() > 10  # not a blank canvas
