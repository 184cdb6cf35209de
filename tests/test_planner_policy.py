"""How a deployed policy turns each head's distribution into an action: argmax, the weighted
median over the head's ordered values, or a draw; and the planner acting by the median."""
import numpy as np
import pytest

from bimacppo_learning.checkpoint import export_policy
from bimacppo_learning.env import IntersectionEnv
from bimacppo_learning.ppo import PPO
from bimacppo_planner.agent import HighLevelPlanner, load_policy
from bimacppo_planner.decision import EnvConfig
from bimacppo_planner.policy import MedianPolicy, SampledPolicy, head_median, with_selection


def logits_of(p):
    return np.log(np.asarray(p, np.float64))


@pytest.mark.parametrize("p, median", [
    ([0.35, 0.20, 0.15, 0.15, 0.15], 1),   # the argmax (0) stops; most of the mass moves
    ([0.60, 0.10, 0.10, 0.10, 0.10], 0),   # one value holds more than half: the argmax
    ([0.2] * 5, 2),                        # uniform: the middle value
    ([0.5, 0.5], 0),                       # exactly half reached: the smaller value
    ([0.1, 0.1, 0.1, 0.1, 0.6], 4),
    ([0.05, 0.40, 0.05, 0.45, 0.05], 2),   # bimodal: between the modes, which neither argmax gives
])
def test_head_median_is_the_smallest_value_whose_cumulative_mass_reaches_half(p, median):
    assert head_median(logits_of(p)) == median


def test_head_median_matches_its_definition_on_random_heads():
    rng = np.random.default_rng(0)
    for _ in range(500):
        z = rng.normal(size=int(rng.integers(1, 8))) * 3
        m = head_median(z)
        c = np.cumsum(np.exp(z) / np.exp(z).sum())
        assert c[m] >= 0.5 - 1e-9 and (m == 0 or c[m - 1] < 0.5)


@pytest.fixture(scope="module")
def policy(tmp_path_factory):
    cfg = EnvConfig.load()
    path = tmp_path_factory.mktemp("pol") / "policy.pt"
    export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=3), path)
    return load_policy(path)


def test_selections_wrap_one_policy(policy):
    rng = np.random.default_rng(1)
    assert with_selection(policy, "argmax") is policy
    med, smp = with_selection(policy, "median"), with_selection(policy, "sample", seed=4)
    assert isinstance(med, MedianPolicy) and isinstance(smp, SampledPolicy) and smp.seed == 4
    differs = 0
    for _ in range(200):
        obs = rng.normal(size=policy.obs_dim) * 3
        a = med.act(obs)
        np.testing.assert_array_equal(a, [head_median(h) for h in policy.logits(obs)])
        differs += int(np.any(a != policy.act(obs)))
    assert differs > 0                       # the median is not a renamed argmax
    with pytest.raises(ValueError, match="one of"):
        with_selection(policy, "mode")


def test_planner_acting_by_median_decodes_the_median_action(policy):
    env = IntersectionEnv()
    hp = HighLevelPlanner(policy, env.road, action_selection="median")
    obs, _ = env.reset(options={"n_sv": 3, "task": "left", "scenario_seed": 1})
    hp.reset(env.world.ego, env.world.goal)
    for _ in range(40):
        x_imr, info = hp.step(env.world.ego, env.world.sv_states())
        np.testing.assert_array_equal(info["obs"], obs)
        np.testing.assert_array_equal(info["action"], policy.act_median(obs))
        obs, _, term, trunc, einfo = env.step(info["action"])
        np.testing.assert_array_equal(einfo["x_imr"], x_imr)
        if term or trunc:
            break
    with pytest.raises(ValueError, match="action_selection must be one of"):
        HighLevelPlanner(policy, env.road, action_selection="sample")


def test_a_recorded_selection_is_how_planner_and_evaluation_run_the_file(policy, tmp_path):
    import torch

    from bimacppo_learning import evaluate as ev
    from bimacppo_learning.checkpoint import set_action_selection
    from bimacppo_planner.policy import CheckpointError

    src = tmp_path / "argmax.pt"
    torch.save({**torch.load(policy.path, weights_only=True)}, src)
    med = set_action_selection(src, tmp_path / "median.pt", "median")
    assert load_policy(src).selection == "argmax" and load_policy(med).selection == "median"
    env = IntersectionEnv()
    assert HighLevelPlanner(load_policy(med), env.road).action_selection == "median"
    assert HighLevelPlanner(load_policy(med), env.road, action_selection="argmax").action_selection == "argmax"
    cell = {"map_id": "dual_lane_4way", "n_svs": [3], "tasks": [0], "episodes": 2, "workers": 1,
            "random_row": False}
    runs = {name: [(c.task, c.n_sv, dict(c.counts), c.returns) for c in ev.evaluate(path, **cell, **kw)]
            for name, path, kw in (("file", med, {}), ("median", src, {"action_selection": "median"}),
                                   ("argmax", med, {"action_selection": "argmax"}),
                                   ("plain", src, {}))}
    assert runs["file"] == runs["median"] and runs["argmax"] == runs["plain"]
    with pytest.raises(FileExistsError, match="not overwritten"):
        set_action_selection(src, med, "argmax")
    with pytest.raises(ValueError, match="one of"):
        set_action_selection(src, tmp_path / "s.pt", "sample")
    blob = torch.load(med, weights_only=True)
    blob["meta"]["action_selection"] = "sample"
    torch.save(blob, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="bad.pt.*action_selection 'sample'"):
        load_policy(tmp_path / "bad.pt")
