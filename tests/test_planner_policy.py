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


@pytest.fixture(scope="module")
def members(tmp_path_factory):
    """Three exports of one configuration (other seeds), recording the packaged env config."""
    from bimacppo_planner.policy import Policy

    cfg = EnvConfig.load()
    d = tmp_path_factory.mktemp("members")
    meta = {"env_config": cfg.to_dict(), "mpc": "fast", "map": "dual_lane_4way"}
    paths = [export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=s), d / f"s{s}.pt", meta={**meta, "seed": s})
             for s in (5, 6, 7)]
    return paths, [Policy.load(p) for p in paths]


def test_an_ensemble_acts_on_the_mixture_of_its_members_distributions(members, tmp_path):
    from bimacppo_learning.checkpoint import make_ensemble
    from bimacppo_planner.policy import EnsemblePolicy

    paths, pols = members
    ens = load_policy(make_ensemble(paths, tmp_path / "e.pt", "median"))
    assert isinstance(ens, EnsemblePolicy) and ens.selection == "median"
    assert [m["seed"] for m in ens.meta["members"]] == [5, 6, 7] and ens.meta["map"] == "dual_lane_4way"
    rng = np.random.default_rng(2)
    member_disagrees = 0
    for _ in range(200):
        obs = rng.normal(size=ens.obs_dim) * 3
        for h, z in enumerate(ens.logits(obs)):
            probs = [np.exp(p.logits(obs)[h] - p.logits(obs)[h].max()) for p in pols]
            mix = np.mean([q / q.sum() for q in probs], axis=0)
            np.testing.assert_allclose(np.exp(z), mix, rtol=1e-5, atol=1e-7)
        a = ens.act_median(obs)
        np.testing.assert_array_equal(a, [head_median(np.log(np.mean(
            [np.exp(p.logits(obs)[h]) / np.exp(p.logits(obs)[h]).sum() for p in pols], axis=0)))
            for h in range(len(ens.nvec))])
        z0 = ens.logits(obs)[0]
        gap = min(np.abs(np.exp(z0) - np.exp(p.logits(obs)[0]) / np.exp(p.logits(obs)[0]).sum()).max()
                  for p in pols)
        member_disagrees += int(gap > 1e-6)
    assert member_disagrees == 200           # the mixture is none of its members


def test_an_ensemble_of_copies_acts_as_the_policy_and_runs_in_the_planner(members, tmp_path):
    from bimacppo_learning.checkpoint import make_ensemble

    paths, pols = members
    twin = load_policy(make_ensemble([paths[0], paths[0]], tmp_path / "twin.pt", "argmax"))
    rng = np.random.default_rng(3)
    for _ in range(100):
        obs = rng.normal(size=twin.obs_dim) * 3
        np.testing.assert_array_equal(twin.act(obs), pols[0].act(obs))
        np.testing.assert_array_equal(twin.act_median(obs), pols[0].act_median(obs))
    from bimacppo_learning import evaluate as ev

    cell = {"map_id": "dual_lane_4way", "n_svs": [2], "tasks": [1], "episodes": 2, "workers": 1,
            "random_row": False}
    as_file, as_member = (ev.evaluate(str(p), **cell, action_selection="argmax")
                          for p in (tmp_path / "twin.pt", paths[0]))
    assert [(c.counts, c.returns) for c in as_file] == [(c.counts, c.returns) for c in as_member]
    ens = load_policy(make_ensemble(paths, tmp_path / "e.pt"))
    env = IntersectionEnv()
    hp = HighLevelPlanner(ens, env.road)
    assert hp.action_selection == "median"
    obs, _ = env.reset(options={"n_sv": 2, "task": "straight", "scenario_seed": 4})
    hp.reset(env.world.ego, env.world.goal)
    for _ in range(10):
        x_imr, info = hp.step(env.world.ego, env.world.sv_states())
        np.testing.assert_array_equal(info["action"], ens.act_median(obs))
        obs, _, term, trunc, einfo = env.step(info["action"])
        np.testing.assert_array_equal(einfo["x_imr"], x_imr)
        if term or trunc:
            break


def test_an_ensemble_refuses_members_trained_otherwise_and_never_overwrites(members, tmp_path):
    import torch

    from bimacppo_learning.checkpoint import make_ensemble
    from bimacppo_planner.policy import CheckpointError, EnsemblePolicy

    paths, _ = members
    cfg = EnvConfig.load()
    other = export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=8), tmp_path / "o.pt",
                          meta={"env_config": {**cfg.to_dict(), "reward": {}}, "mpc": "fast", "map": "dual_lane_4way"})
    with pytest.raises(CheckpointError, match="member 1 records another env_config"):
        make_ensemble([paths[0], other], tmp_path / "x.pt")
    small = export_policy(PPO(cfg.obs_dim - 1, cfg.nvec, seed=8), tmp_path / "small.pt")
    with pytest.raises(CheckpointError, match="member 1 takes observations of size"):
        make_ensemble([paths[0], small], tmp_path / "x.pt")
    e = make_ensemble(paths[:2], tmp_path / "e.pt")
    with pytest.raises(CheckpointError, match="is an ensemble"):
        make_ensemble([paths[0], e], tmp_path / "x.pt")
    with pytest.raises(FileExistsError, match="not overwritten"):
        make_ensemble(paths, e)
    (tmp_path / "junk.pt").write_bytes(b"junk")
    with pytest.raises(CheckpointError, match="junk.pt"):
        make_ensemble([paths[0], tmp_path / "junk.pt"], tmp_path / "x.pt")
    assert not (tmp_path / "x.pt").exists()
    blob = torch.load(e, weights_only=True)
    with pytest.raises(CheckpointError, match="at least 2"):
        EnsemblePolicy({**blob, "members": blob["members"][:1]}, "one.pt")
    blob["members"][1]["actor"].pop("0.weight")
    torch.save(blob, tmp_path / "broken.pt")
    with pytest.raises(CheckpointError, match=r"broken.pt\[member 1\]: actor lacks"):
        load_policy(tmp_path / "broken.pt")


def _constant_member(path, cfg, a3_probs, seed):
    """A policy export whose heads ignore the observation: A1 and A2 uniform, A3 as given."""
    import torch

    from bimacppo_planner.policy import Policy

    src = export_policy(PPO(cfg.obs_dim, cfg.nvec, seed=seed), path,
                        meta={"env_config": cfg.to_dict(), "mpc": "fast", "map": "three_lane_straight"})
    blob = torch.load(src, weights_only=True)
    last = max(int(k.split(".")[0]) for k in blob["actor"])
    blob["actor"][f"{last}.weight"].zero_()
    bias = torch.zeros(sum(cfg.nvec))
    bias[-3:] = torch.log(torch.tensor(a3_probs))
    blob["actor"][f"{last}.bias"] = bias
    torch.save(blob, path)
    return Policy.load(path)


def test_a_vote_picks_a_side_most_members_chose_where_the_mixture_keeps_between_them(tmp_path):
    """Three members pass right by a small margin, two pass left with certainty: the mixture's
    median on A3 (left / keep / right) is keep, which none chose; the vote is right. Where the
    most chosen values tie, the vote is the mixture's."""
    from bimacppo_learning.checkpoint import make_ensemble
    from bimacppo_planner.policy import CheckpointError, EnsemblePolicy

    cfg = EnvConfig.load()
    right, left = [0.001, 0.449, 0.55], [0.9, 0.099, 0.001]
    paths = [_constant_member(tmp_path / f"m{i}.pt", cfg, p, i).path
             for i, p in enumerate([right, right, right, left, left])]
    obs = np.zeros(cfg.obs_dim)
    mix = load_policy(make_ensemble(paths, tmp_path / "mix.pt"))
    vote = load_policy(make_ensemble(paths, tmp_path / "vote.pt", combine="vote"))
    assert (mix.combine, vote.combine) == ("mixture", "vote")
    assert mix.act_median(obs)[2] == 1 and vote.act_median(obs)[2] == 2
    np.testing.assert_array_equal(vote.act_median(obs)[:2], mix.act_median(obs)[:2])   # uniform heads: all tie
    assert mix.act(obs)[2] == 0 and vote.act(obs)[2] == 2   # argmax: the mixture's mode is left (0.36)
    most_left = load_policy(make_ensemble(paths[2:], tmp_path / "l.pt", combine="vote"))   # one right, two left
    assert most_left.act_median(obs)[2] == 0
    tie = load_policy(make_ensemble(paths[2:4], tmp_path / "tie.pt", "argmax", combine="vote"))   # right 1 : left 1
    mixture = np.exp(tie.logits(obs)[2])        # [0.45, 0.27, 0.28]: mode left, median keep
    assert tie.act(obs)[2] == int(np.argmax(mixture)) == 0
    assert tie.act_median(obs)[2] == head_median(tie.logits(obs)[2]) == 1
    draws = [vote.act(obs, deterministic=False, rng=np.random.default_rng(k))[2] for k in range(300)]
    assert set(draws) == {0, 1, 2}                 # sampling draws from the mixture, votes nothing
    with pytest.raises(ValueError, match="combine must be one of"):
        make_ensemble(paths, tmp_path / "x.pt", combine="mean")
    import torch
    blob = torch.load(tmp_path / "vote.pt", weights_only=True)
    blob["meta"]["combine"] = "mean"
    with pytest.raises(CheckpointError, match="combine 'mean'"):
        EnsemblePolicy(blob, "bad.pt")
