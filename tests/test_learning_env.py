"""The high-level Gymnasium environment: API conformance, curriculum control, reward, determinism,
registration with Gymnasium and the config ``gym.make`` passes."""
import shutil
import site
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from bimacppo_learning.env import MAP_IDS, IntersectionEnv, register_envs
from bimacppo_planner.decision import ConfigError, EnvConfig
from conftest import REPO


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


def _fresh_python(code: str, cwd) -> subprocess.CompletedProcess:
    """``code`` in a new interpreter of this environment, outside the repository (whose
    same-named ROS package folders must not shadow the installed packages)."""
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=cwd, capture_output=True,
                          text=True, timeout=300)


def test_a_fresh_interpreter_makes_the_ids_with_no_extra_import(tmp_path):
    out = _fresh_python("""
        import sys
        assert "bimacppo_learning" not in sys.modules, "the start-up hook imported the package"
        import gymnasium as gym
        for env_id in ("bimacppo/DualLaneIntersection-v0", "bimacppo/SingleLaneIntersection-v0",
                       "bimacppo/ThreeLaneOvertake-v0"):
            assert env_id in gym.registry, env_id
        assert "bimacppo_learning.env" not in sys.modules, "registration imported the env module"
        e = gym.make("bimacppo/DualLaneIntersection-v0")
        obs, info = e.reset(seed=0, options={"n_sv": 1, "task": "left"})
        print("OK", e.unwrapped.road.id, obs.shape, info["n_sv"])
    """, tmp_path)
    assert out.returncode == 0, out.stderr[-3000:] + "\n(if the ids are missing: reinstall, scripts/install.sh)"
    assert out.stdout.split() == ["OK", "dual_lane_4way", "(16,)", "1"]


def test_module_prefixed_id_registers_without_the_startup_hook(tmp_path):
    """``gym.make("bimacppo_learning:<id>")`` imports the package, which registers the ids: this
    works where the .pth hook is absent (here: taken off sys.meta_path before gymnasium loads)."""
    out = _fresh_python("""
        import sys
        sys.meta_path[:] = [f for f in sys.meta_path if getattr(f, "name", "") != "bimacppo_learning gymnasium ids"]
        import gymnasium as gym
        assert "bimacppo/ThreeLaneOvertake-v0" not in gym.registry
        try:
            gym.make("bimacppo/ThreeLaneOvertake-v0")
        except gym.error.Error as exc:
            print("without:", type(exc).__name__)
        e = gym.make("bimacppo_learning:bimacppo/ThreeLaneOvertake-v0")
        print("with:", e.unwrapped.road.id)
    """, tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.splitlines() == ["without: NamespaceNotFound", "with: three_lane_straight"]


def test_wheel_installs_the_same_startup_hook_as_the_editable_install(tmp_path):
    """A regular ``pip install`` gets the .pth (wheel root = site-packages) that the editable
    install of this environment holds; a mismatch means the environment needs a reinstall."""
    src = tmp_path / "src"
    shutil.copytree(REPO / "bimacppo_learning", src, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                           "--disable-pip-version-check", str(src), "-w", str(tmp_path / "dist")],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("bimacppo_learning-*.whl")
    with zipfile.ZipFile(wheel) as z:
        pth = z.read("bimacppo_learning-gymnasium.pth").decode()
    assert pth.startswith("import sys; exec(") and pth.count("\n") == 1
    installed = [Path(p) / "bimacppo_learning-gymnasium.pth" for p in site.getsitepackages()]
    installed = [p for p in installed if p.is_file()]
    assert installed, "this environment lacks the start-up hook: run scripts/install.sh"
    assert installed[0].read_text() == pth, "the installed hook is stale: run scripts/install.sh"


@pytest.mark.parametrize("kind", ["str", "path", "dict"])
def test_make_accepts_a_yaml_path_or_a_dict_as_config(tmp_path, kind):
    yml = tmp_path / "env.yaml"
    yml.write_text("observation:\n  max_sv: 2\n  sv_clip: 30.0\n")
    config = {"str": str(yml), "path": yml, "dict": {"observation": {"max_sv": 2, "sv_clip": 30.0}}}[kind]
    register_envs()
    e = gym.make("bimacppo/DualLaneIntersection-v0", config=config)
    cfg = e.unwrapped.cfg
    assert (cfg.observation.max_sv, cfg.observation.sv_clip) == (2, 30.0)
    assert cfg.reward == EnvConfig.load().reward          # what the config leaves out: the defaults
    obs, _ = e.reset(seed=0, options={"n_sv": 2, "task": "left", "scenario_seed": 1})
    assert obs.shape == (12,) == e.observation_space.shape   # ego + 2 SV slots
    e.close()


def test_make_rejects_a_bad_config_naming_the_problem(tmp_path):
    register_envs()
    with pytest.raises(ConfigError, match="sv_clipp"):
        gym.make("bimacppo/DualLaneIntersection-v0", config={"observation": {"sv_clipp": 3.0}})
    with pytest.raises(ConfigError, match="missing.yaml"):
        gym.make("bimacppo/DualLaneIntersection-v0", config=tmp_path / "missing.yaml")
    with pytest.raises(TypeError, match="config must be"):
        gym.make("bimacppo/DualLaneIntersection-v0", config=3)


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


def test_per_step_infos_keep_one_shape_so_vector_envs_can_stack_them():
    """Envs whose episodes end in different ticks of a decision still give infos of one shape:
    Gymnasium's vector envs stack each info key across envs into one array."""
    from gymnasium.vector import AutoresetMode, SyncVectorEnv
    cfg = EnvConfig.load(REPO / "bimacppo_learning/bimacppo_learning/config/env_extended.yaml")
    k = cfg.action.decision_every
    assert k > 1
    venv = SyncVectorEnv([lambda: IntersectionEnv(config=cfg)] * 2, autoreset_mode=AutoresetMode.DISABLED)
    try:
        # env 0 drives at the far waypoint into the crossing traffic, env 1 stands: their
        # episodes end at different decisions; over a few scenarios one ends within a decision
        # (a collision or the goal between two decision ticks) while the other runs all ticks
        partial = False
        for seed in range(10):
            venv.reset(seed=[seed, seed + 100], options={"n_sv": 3, "task": 1})
            for _ in range(400):
                _, _, term, trunc, info = venv.step(np.array([[4, 4, 1], [0, 0, 1]]))
                assert info["commands"].shape == (2, k, 2)
                ended = term | trunc
                for i in np.nonzero(ended)[0]:
                    rows = ~np.isnan(info["commands"][i]).any(axis=1)
                    assert rows[0] and np.all(rows[:rows.sum()])        # the ticks run come first
                    partial |= rows.sum() < k
                if ended.any():
                    break
            if partial:
                break
        assert partial, "no episode ended within a decision: the case is not exercised"
    finally:
        venv.close()
