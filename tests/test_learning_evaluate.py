"""The evaluation protocol with any policy: files, predict()/act() objects, the random baseline,
and failures in worker processes (they end the run with one error, never a hang)."""
import csv
import io
import os
import pickle
import re
from collections import Counter

import numpy as np
import pytest

from bimacppo_learning import evaluate as ev
from bimacppo_learning.cli import evaluate_main
from bimacppo_planner.agent import env_config_of, load_policy, shipped_policy_path
from bimacppo_planner.decision import EnvConfig
from bimacppo_planner.policy import CheckpointError

CELL = {"map_id": "dual_lane_4way", "n_svs": [1], "tasks": [1], "episodes": 1}


class PredictPolicy:
    """Stable-Baselines3 style: predict(obs, state=None, episode_start=None, deterministic=False)."""

    def __init__(self, policy):
        self.policy = policy
        self.calls = []

    def predict(self, obs, state=None, episode_start=None, deterministic=False):
        self.calls.append(deterministic)
        return self.policy.act(obs, deterministic=deterministic), state


class Raiser:
    def act(self, obs):
        raise RuntimeError("boom in the policy")


class Dies:
    def act(self, obs):
        os._exit(3)


class BadAction:
    def act(self, obs):
        return [9, 9, 9]


class Unpicklable:
    def __init__(self, policy):
        self.act = lambda obs: policy.act(obs)   # a lambda attribute: pickle refuses the object


def _outcomes(cells):
    return [(c.policy, c.task, c.n_sv, dict(c.counts), c.returns) for c in cells]


def _one_error_line(err: str, prog: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"{prog}: error: "), err
    return lines[0]


@pytest.fixture(autouse=True)
def fresh_random_cache():
    ev._RANDOM_CACHE.clear()
    yield
    ev._RANDOM_CACHE.clear()


def test_an_object_with_predict_or_act_is_evaluated_like_its_file():
    path = shipped_policy_path()
    # an object acts by its own act/predict (the argmax), whatever selection its file records
    from_file = ev.evaluate(path, workers=1, random_row=False, action_selection="argmax", **CELL)
    wrapped = PredictPolicy(load_policy(path))
    # an object carries no env or NMPC config: it runs on the ones given (here the file's; its
    # env config differs from the packaged default that an object gets otherwise)
    cfg = env_config_of(load_policy(path))
    assert cfg != EnvConfig.load()
    mpc = ev.resolve_mpc_config(load_policy(path))
    from_predict = ev.evaluate(wrapped, workers=1, random_row=False, env_config=cfg, mpc_config=mpc, **CELL)
    from_act = ev.evaluate(load_policy(path), workers=1, random_row=False, **CELL)
    assert _outcomes(from_file) == _outcomes(from_predict) == _outcomes(from_act)
    assert wrapped.calls and all(wrapped.calls)          # asked for its deterministic action
    assert [c.policy for c in from_file] == ["policy"]


class CountingSampled:
    """What action_selection='sample' must amount to: the file's policy sampled per head, the
    generator seeded per episode from (seed, scenario seed); it counts the draws that differ
    from the argmax, to show that sampling changed something."""

    def __init__(self, policy, seed):
        self.policy, self.seed, self.off_argmax = policy, seed, 0
        self.obs_dim, self.nvec = policy.obs_dim, policy.nvec

    def begin_episode(self, scenario_seed):
        self.rng = np.random.default_rng([self.seed, int(scenario_seed)])

    def act(self, obs):
        a = self.policy.act(obs, deterministic=False, rng=self.rng)
        self.off_argmax += int(np.any(a != self.policy.act(obs)))
        return a


def test_sampled_actions_are_the_trained_distribution_seeded_per_episode_and_reproducible(capsys):
    path = shipped_policy_path()
    cell = {**CELL, "n_svs": [3], "episodes": 3}
    cfg = env_config_of(load_policy(path))
    runs = [ev.evaluate(path, workers=w, random_row=False, action_selection="sample", sample_seed=s, **cell)
            for w, s in ((1, 5), (2, 5), (1, 6))]
    assert _outcomes(runs[0]) == _outcomes(runs[1])               # same seed: same run, any worker count
    reference = CountingSampled(load_policy(path), 5)
    by_hand = ev.evaluate(reference, workers=1, random_row=False, env_config=cfg,
                          mpc_config=ev.resolve_mpc_config(load_policy(path)), **cell)
    assert _outcomes(by_hand) == _outcomes(runs[0])
    assert reference.off_argmax > 0                                 # sampling is not the argmax
    assert _outcomes(runs[2]) != _outcomes(runs[0])                # another seed draws other actions
    with pytest.raises(ev.EvaluationError, match="needs a policy file"):
        ev.evaluate(load_policy(path), workers=1, random_row=False, action_selection="sample", **cell)
    with pytest.raises(ValueError, match="action_selection"):
        ev.evaluate(path, workers=1, random_row=False, action_selection="mode", **cell)
    assert evaluate_main(["--sample", "--sample-seed", "5", "--episodes", "1", "--n-sv", "1", "--tasks", "straight",
                          "--workers", "1", "--no-random-row"]) == 0
    assert "actions sampled (seed 5)" in capsys.readouterr().out


def test_random_row_is_seeded_on_the_same_scenarios_and_shown_in_every_table(tmp_path):
    res = ev.evaluate(None, workers=2, **CELL)
    assert [(c.policy, c.task, c.n_sv, c.n) for c in res] == [("policy", 1, 1, 1), ("random", 1, 1, 1)]
    # the same baseline as evaluating the random policy itself in this process: same seeds and actions
    ev._RANDOM_CACHE.clear()
    alone = ev.evaluate(ev.RandomPolicy((5, 5, 3), seed=0), workers=1, random_row=False,
                        env_config=env_config_of(load_policy(None)),
                        mpc_config=ev.resolve_mpc_config(load_policy(None)), **CELL)
    assert _outcomes(alone)[0][1:] == _outcomes(res)[1][1:]
    md = ev.to_markdown(res, "t")
    assert "| straight |" in md and "| straight, random policy |" in md
    out = tmp_path / "eval"
    md_path, csv_path = ev.write_outputs(res, out, "t")
    assert "random policy" in md_path.read_text()
    assert [r["task"] for r in csv.DictReader(csv_path.open())] == ["straight"]     # the policy's cells only
    rand = list(csv.DictReader((tmp_path / "eval_random.csv").open()))
    assert [(r["task"], r["n_sv"], r["episodes"]) for r in rand] == [("straight", "1", "1")]


def test_a_random_policy_differs_by_seed_and_stays_in_its_action_space():
    a, b = ev.RandomPolicy((5, 5, 3), seed=0), ev.RandomPolicy((5, 5, 3), seed=1)
    a.begin_episode(7)
    b.begin_episode(7)
    xs, ys = np.array([a.act(None) for _ in range(50)]), np.array([b.act(None) for _ in range(50)])
    assert not np.array_equal(xs, ys)
    assert xs.min() >= 0 and np.all(xs.max(axis=0) < [5, 5, 3])
    a.begin_episode(7)
    np.testing.assert_array_equal(np.array([a.act(None) for _ in range(50)]), xs)


def test_an_unpicklable_object_runs_in_this_process():
    shipped = load_policy(None)
    pol = Unpicklable(shipped)
    with pytest.raises(Exception):
        pickle.dumps(pol)
    with pytest.warns(RuntimeWarning, match="in this process"):
        # an object carries no env config: the evaluation is told the one the policy was trained in
        res = ev.evaluate(pol, workers=2, random_row=False, env_config=env_config_of(shipped),
                          **{**CELL, "tasks": [0, 1]})
    assert [(c.task, c.n) for c in res] == [(0, 1), (1, 1)]


@pytest.mark.parametrize("policy, match", [
    (Raiser(), r"policy on (left|straight), N_sv=0: RuntimeError: boom in the policy"),
    (Dies(), r"worker died \(exit code 3\)"),
    (BadAction(), r"returned the action \[9, 9, 9\]; expected 3 integers of MultiDiscrete\(\[5, 5, 3\]\)"),
])
def test_a_failure_in_a_worker_ends_the_evaluation_with_its_cause(policy, match):
    with pytest.raises(ev.EvaluationError, match=match):
        ev.evaluate(policy, "dual_lane_4way", [0], [0, 1], 1, workers=2, random_row=False)


def test_a_policy_for_another_observation_size_is_refused_before_any_episode():
    class SevenInputs:
        obs_dim = 7

        def act(self, obs):
            raise AssertionError("never called")

    with pytest.raises(ev.EvaluationError, match="size 7; the env config gives 16"):
        ev.evaluate(SevenInputs(), workers=1, **CELL)
    with pytest.raises(TypeError, match="not a policy"):
        ev.evaluate(object(), workers=1, **CELL)


def test_cli_a_checkpoint_error_in_a_worker_is_one_error_line(monkeypatch, tmp_path, capsys):
    """A policy file that is gone by the time the workers load it: the error crosses the process
    boundary and the command ends with exit status 2 (it used to wait forever)."""
    gone = tmp_path / "gone.pt"
    real = ev.resolve_policy

    def resolve(policy, env_config=None):
        _, loaded, cfg = real(None, env_config)
        return ("path", str(gone)), loaded, cfg

    monkeypatch.setattr(ev, "resolve_policy", resolve)
    rc = evaluate_main(["--episodes", "1", "--n-sv", "0", "--tasks", "left", "straight", "--workers", "2",
                        "--no-random-row"])
    assert rc == 2
    line = _one_error_line(capsys.readouterr().err, "bimacppo-evaluate")
    assert line == f"bimacppo-evaluate: error: {gone}: no such file"


def test_cli_without_a_policy_evaluates_the_shipped_one_beside_the_random_row(capsys):
    assert evaluate_main(["--episodes", "1", "--n-sv", "2", "--tasks", "right", "--workers", "2"]) == 0
    out = capsys.readouterr().out
    assert "| right |" in out and "| right, random policy |" in out
    assert evaluate_main(["--episodes", "1", "--n-sv", "2", "--tasks", "right", "--workers", "1",
                          "--no-random-row"]) == 0
    out = capsys.readouterr().out
    assert "| right |" in out and "random" not in out


def test_median_actions_are_the_median_policy_and_named_in_the_table(capsys):
    from bimacppo_planner.policy import MedianPolicy

    path = shipped_policy_path()
    cell = {**CELL, "n_svs": [3], "episodes": 2}
    cfg = env_config_of(load_policy(path))
    by_file = ev.evaluate(path, workers=1, random_row=False, action_selection="median", **cell)
    by_hand = ev.evaluate(MedianPolicy(load_policy(path)), workers=1, random_row=False, env_config=cfg,
                          mpc_config=ev.resolve_mpc_config(load_policy(path)), **cell)
    assert _outcomes(by_file) == _outcomes(by_hand)
    with pytest.raises(ev.EvaluationError, match="needs a policy file"):
        ev.evaluate(load_policy(path), workers=1, random_row=False, action_selection="median", **cell)
    assert evaluate_main(["--action", "median", "--episodes", "1", "--n-sv", "1", "--tasks", "straight",
                          "--workers", "1", "--no-random-row"]) == 0
    assert "median actions" in capsys.readouterr().out


@pytest.mark.parametrize("argv, says", [
    (["--n-sv", "7"], "N_sv=7 impossible on map 'dual_lane_4way' (0..3)"),
    (["--map", "three_lane_straight"], "has no task 'left'"),
    (["--episodes", "0"], "--episodes must be in 1..1000"),
    (["--workers", "0"], "--workers must be >= 1"),
    (["--slow-svs", "-1"], "--slow-svs must be >= 0"),
    (["--sample", "--action", "median"], "--sample contradicts --action median"),
    (["/nonexistent/policy.pt"], "/nonexistent/policy.pt: no such file"),
])
def test_cli_refusals_are_one_error_line(argv, says, capsys):
    assert evaluate_main(argv) == 2
    assert says in _one_error_line(capsys.readouterr().err, "bimacppo-evaluate")


def test_checkpoint_error_survives_pickling():
    e = pickle.loads(pickle.dumps(CheckpointError("/x/p.pt", "no such file")))
    assert (type(e), e.path, e.problem, str(e)) == (CheckpointError, "/x/p.pt", "no such file", "/x/p.pt: no such file")


def test_slow_svs_runs_the_overtaking_protocol_the_way_training_draws_it():
    """evaluate(slow_svs=N) slows draw_n_slow(seed, N_sv, N) SVs per episode, as training's
    --slow-svs does: the same counts as a hand-written loop that sets n_slow itself."""

    from bimacppo_common.conventions import TASKS
    from bimacppo_sim import draw_n_slow
    from bimacppo_learning.env import IntersectionEnv

    policy = load_policy(shipped_policy_path())
    j, n = TASKS.index("straight"), 4
    [cell] = ev.evaluate(shipped_policy_path(), "three_lane_straight", (3,), (j,), n, workers=1,
                         random_row=False, seed_set="validation", slow_svs=2, action_selection="argmax")
    # the controller evaluate() runs the file with: the NMPC config it records
    env = IntersectionEnv(map_id="three_lane_straight", config=env_config_of(policy),
                          mpc_config=ev.resolve_mpc_config(policy))
    hand, slowed = Counter(), []
    for k in range(n):
        seed = ev.eval_seed(j, 3, k, "validation")
        obs, _ = env.reset(options={"n_sv": 3, "task": "straight", "scenario_seed": seed,
                                    "n_slow": draw_n_slow(seed, 3, 2)})
        slowed.append(sum(bool(sv.slow) for sv in env.world.svs))
        done = False
        while not done:
            obs, _, term, trunc, info = env.step(policy.act(obs, deterministic=True))
            done = term or trunc
        hand[info["outcome"]] += 1
    env.close()
    assert cell.counts == hand
    assert slowed == [draw_n_slow(ev.eval_seed(j, 3, k, "validation"), 3, 2) for k in range(n)]
    assert any(slowed)                                  # the draw does slow SVs in these episodes
    with pytest.raises(ValueError, match="slow_svs must be >= 0"):
        ev.evaluate(shipped_policy_path(), "three_lane_straight", (3,), (j,), 1, workers=1, slow_svs=-1)


def _wilson(k, n, z=1.959963984540054):
    """The Wilson score interval in closed form, to check the library call against."""
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z / (1 + z * z / n) * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n))
    return 100 * (centre - half), 100 * (centre + half)


@pytest.mark.parametrize("k,n", [(95, 100), (100, 100), (0, 30), (487, 500), (498, 500)])
def test_success_interval_is_the_wilson_interval_and_reaches_the_tables(k, n):
    cell = ev.CellResult(1, 3, Counter(success=k, collision=n - k), [])
    lo, hi = cell.success_interval()
    assert (lo, hi) == pytest.approx(_wilson(k, n), abs=1e-6)
    assert lo <= cell.pct("success") <= hi and 0.0 <= lo and hi <= 100.0
    if 0 < k < n:
        assert lo < cell.pct("success") < hi
    row = next(csv.DictReader(io.StringIO(ev.to_csv([cell]))))
    assert (float(row["success_ci_low"]), float(row["success_ci_high"])) == pytest.approx((lo, hi), abs=0.006)
    md = ev.to_markdown([cell])
    assert f"| straight | {cell.pct('success'):.1f} [{lo:.1f}, {hi:.1f}] of {n} |" in md
    # what the table shows lies inside the interval it shows (498 of 500 must not read as 100)
    shown = re.search(r"\| straight \| ([0-9.]+) \[([0-9.]+), ([0-9.]+)\] of", md).groups()
    assert float(shown[1]) <= float(shown[0]) <= float(shown[2])


def test_a_wider_sample_narrows_the_interval_and_an_empty_cell_has_none():
    small = ev.CellResult(0, 3, Counter(success=95, collision=5), []).success_interval()
    large = ev.CellResult(0, 3, Counter(success=475, collision=25), []).success_interval()
    assert large[1] - large[0] < small[1] - small[0]
    assert all(np.isnan(v) for v in ev.CellResult(0, 3, Counter(), []).success_interval())
