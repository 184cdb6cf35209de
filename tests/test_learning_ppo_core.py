"""PPO core: heads and log-probs, GAE (hand-worked, with truncation), clip objective, config."""
import dataclasses
import io

import numpy as np
import pytest
import torch

from bimacppo_learning.ppo import PPO, MultiCategorical, RunningMeanStd, clipped_surrogate
from bimacppo_learning.ppo_config import PPOConfig, TrainConfig, load_config
from bimacppo_learning.rollout import RolloutBuffer, compute_gae

NVEC = (5, 5, 3)


def test_actor_emits_one_logit_per_choice_and_log_prob_is_sum_of_heads():
    agent = PPO(16, NVEC, PPOConfig(), seed=0)
    assert agent.actor[-1].out_features == sum(NVEC)
    assert [m.out_features for m in agent.actor if isinstance(m, torch.nn.Linear)] == [256, 128, 13]
    assert [m.out_features for m in agent.critic if isinstance(m, torch.nn.Linear)] == [256, 128, 1]
    obs = torch.randn(7, 16)
    d = agent.dist(obs)
    a = d.sample(torch.Generator().manual_seed(1))
    assert a.shape == (7, 3) and a.dtype == torch.long
    for k, n in enumerate(NVEC):
        assert int(a[:, k].min()) >= 0 and int(a[:, k].max()) < n
    lp = d.log_prob(a)
    assert lp.shape == (7,)
    # independent heads: joint log-prob = sum of each head's own log-softmax entry
    logits = agent.actor(obs)
    parts = torch.split(logits, NVEC, dim=-1)
    manual = sum(torch.log_softmax(p, -1).gather(-1, a[:, k:k + 1]).squeeze(-1) for k, p in enumerate(parts))
    torch.testing.assert_close(lp, manual)
    # entropies add; near-uniform init (small output gain) -> close to the maximum
    assert d.entropy().shape == (7,)
    assert float(d.entropy().mean().detach()) == pytest.approx(np.log(5) * 2 + np.log(3), abs=0.05)
    # probabilities of all 75 joint actions sum to one
    one = torch.randn(1, 16)
    dd = agent.dist(one.expand(75, 16))
    grid = torch.tensor([[i, j, k] for i in range(5) for j in range(5) for k in range(3)])
    assert float(dd.log_prob(grid).exp().sum()) == pytest.approx(1.0, abs=1e-5)


def test_multicategorical_rejects_wrong_shapes():
    with pytest.raises(ValueError, match="sum\\(nvec\\)"):
        MultiCategorical(torch.zeros(2, 12), NVEC)
    d = MultiCategorical(torch.zeros(2, 13), NVEC)
    with pytest.raises(ValueError, match="heads"):
        d.log_prob(torch.zeros(2, 2, dtype=torch.long))


def test_gae_hand_computed_with_termination_and_truncation():
    g, lam = 0.9, 0.5
    # one env, 5 steps: episode A = steps 0,1 ends by TRUNCATION at step 1 (final obs value 4.0);
    # episode B = steps 2,3 ends by TERMINATION at step 3; step 4 is cut by the rollout end (V=0.5)
    r = np.array([1.0, 2.0, 0.0, 3.0, 1.0])
    v = np.array([0.5, 1.0, 2.0, 1.5, 0.2])
    nv = np.array([1.0, 4.0, 1.5, 99.0, 0.5])     # 99 must be ignored: termination
    term = np.array([0, 0, 0, 1, 0], bool)
    end = np.array([0, 1, 0, 1, 0], bool)
    adv, ret = compute_gae(r, v, nv, term, end, g, lam)
    d4 = 1.0 + g * 0.5 - 0.2
    d3 = 3.0 - 1.5
    d2 = 0.0 + g * 1.5 - 2.0
    d1 = 2.0 + g * 4.0 - 1.0                       # bootstrap from the final obs on truncation
    d0 = 1.0 + g * 1.0 - 0.5
    exp = np.array([d0 + g * lam * d1, d1, d2 + g * lam * d3, d3, d4])
    np.testing.assert_allclose(adv, exp, rtol=1e-6)
    np.testing.assert_allclose(ret, exp + v, rtol=1e-6)
    # lambda = 1, gamma = 1, no value: advantages are plain reward-to-go within each episode
    adv1, _ = compute_gae(r, np.zeros(5), np.zeros(5), term, end, 1.0, 1.0)
    np.testing.assert_allclose(adv1, [3.0, 2.0, 3.0, 3.0, 1.0])


def test_gae_validates_inputs():
    z = np.zeros(3)
    with pytest.raises(ValueError, match="shape"):
        compute_gae(z, z, np.zeros(4), z.astype(bool), z.astype(bool), 0.9, 0.9)
    with pytest.raises(ValueError, match="terminated"):
        compute_gae(z, z, z, np.array([1, 0, 0], bool), np.zeros(3, bool), 0.9, 0.9)


def test_buffer_bootstraps_truncation_from_final_obs_value_not_next_episode():
    buf = RolloutBuffer(3, 1, 2, 3)
    obs = [np.array([[0.0, 0.0]]), np.array([[1.0, 0.0]]), np.array([[2.0, 0.0]])]
    vals = [0.0, 0.0, 7.0]            # step 2 is the first obs of a NEW episode, value 7
    for t in range(3):
        buf.add(obs[t], np.zeros((1, 3)), [0.0], [vals[t]], [0.0], [False], [t == 1])
    buf.final_obs.append((1, 0, np.array([5.0, 0.0], np.float32)))
    value_fn = lambda o: np.asarray(o)[:, 0] * 10.0   # noqa: E731  V(final obs) = 50
    data = buf.finish(value_fn, np.array([[3.0, 0.0]], np.float32), gamma=1.0, lam=1.0)
    # step 1 (truncated): r + V(final) - V = 50; step 0 folds it in; step 2: cut -> V(last)=30 - 7
    np.testing.assert_allclose(data["advantages"], [50.0, 50.0, 23.0])


def test_clip_objective_behaviour():
    old = torch.zeros(4)
    adv = torch.tensor([1.0, 1.0, -1.0, -1.0])
    # ratios 1.5, 0.5, 1.5, 0.5
    new = torch.log(torch.tensor([1.5, 0.5, 1.5, 0.5]))
    loss, cf, kl = clipped_surrogate(new, old, adv, 0.2)
    # min(r A, clip(r) A): A>0: r=1.5 -> 1.2 (clipped), r=0.5 -> 0.5; A<0: r=1.5 -> -1.5, r=0.5 -> -0.8
    assert float(loss) == pytest.approx(-(1.2 + 0.5 - 1.5 - 0.8) / 4)
    assert float(cf) == 1.0 and float(kl) > 0
    # gradient vanishes where the clip is active and the objective would improve further
    new_p = new.clone().requires_grad_(True)
    clipped_surrogate(new_p, old, adv, 0.2)[0].backward()
    g = new_p.grad
    assert g[0] == 0 and g[3] == 0 and g[1] != 0 and g[2] != 0
    # ratio 1 -> loss = -mean(A), no clipping, zero KL
    loss1, cf1, kl1 = clipped_surrogate(old, old, adv, 0.2)
    assert float(loss1) == pytest.approx(0.0) and float(cf1) == 0.0 and float(kl1) == pytest.approx(0.0)


def test_update_increases_probability_of_advantaged_actions():
    cfg = PPOConfig(minibatch_size=64, epochs=5, entropy_coef=0.0)
    agent = PPO(4, NVEC, cfg, seed=3)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(256, 4)).astype(np.float32)
    p_wp2 = lambda: float(agent.dist(torch.as_tensor(obs)).log_probs[0].exp()[:, 2].mean().detach())  # noqa: E731
    p_before = p_wp2()
    for _ in range(8):   # on-policy iterations: reward waypoint 2 only
        acts, logp, _ = agent.act(obs)
        adv = np.where(acts[:, 0] == 2, 1.0, -1.0).astype(np.float32)
        stats = agent.update(obs, acts, logp, adv, np.zeros(256, np.float32))
    assert p_before == pytest.approx(0.2, abs=0.05) and p_wp2() > 0.6
    assert stats["epochs"] == 5 and 0.0 <= stats["clip_fraction"] <= 1.0
    # target_kl stops the epochs early once the policy moved enough
    agent2 = PPO(4, NVEC, dataclasses.replace(cfg, epochs=20, target_kl=1e-4), seed=3)
    acts2, logp2, _ = agent2.act(obs)
    stats2 = agent2.update(obs, acts2, logp2, adv, np.zeros(256, np.float32))
    assert stats2["early_stop"] == 1.0 and stats2["epochs"] < 20


def test_running_mean_std_matches_batch_statistics():
    rng = np.random.default_rng(1)
    x = rng.normal(3.0, 2.0, size=(1000, 3))
    rms = RunningMeanStd(3, 1e-8, 10.0)
    for chunk in np.array_split(x, 7):
        rms.update(chunk)
    np.testing.assert_allclose(rms.mean, x.mean(0), rtol=1e-10)
    np.testing.assert_allclose(rms.var, x.var(0), rtol=1e-10)
    z = rms.normalize(x)
    assert abs(z.mean()) < 1e-6 + 0.01 and np.all(np.abs(z) <= 10.0)


def test_packaged_config_has_paper_values():
    p, t = load_config()
    assert p.hidden_sizes == (256, 128)
    assert (p.actor_lr, p.critic_lr, p.epochs, p.gamma, p.clip_eps) == (5e-4, 1e-3, 20, 0.99, 0.2)
    assert t.vector == "batched" and t.batch_workers <= t.num_envs
    assert t.num_envs * t.rollout_steps == 2048        # samples per PPO update, whatever the vector mode
    assert isinstance(p, PPOConfig) and isinstance(t, TrainConfig)
    with pytest.raises(dataclasses.FrozenInstanceError):
        p.gamma = 0.5


@pytest.mark.parametrize("text, match", [
    ("ppo:\n  gama: 0.9\n", r"unknown key 'ppo\.gama' \(did you mean 'gamma'\?\)"),
    ("ppo:\n  gamma: 1.5\n", r"key 'ppo\.gamma' must be in \[0\.0, 1\.0\], got 1\.5"),
    ("ppo:\n  epochs: 2.5\n", r"key 'ppo\.epochs' must be an integer, got 2\.5"),
    ("ppo:\n  activation: gelu\n", "activation"),
    ("ppo:\n  clip_eps: 0\n", "clip_eps"),
    ("ppo:\n  hidden_sizes: [256, 0]\n", r"ppo\.hidden_sizes' item 1 must be >= 1"),
    ("train:\n  vector: threads\n", "vector"),
    ("train:\n  num_envs: 0\n", "num_envs"),
    ("train:\n  batch_workers: 0\n", r"train\.batch_workers' must be >= 1"),
    ("train:\n  num_env: 2\n", r"unknown key 'train\.num_env' \(did you mean 'num_envs'\?\)"),
    ("trian:\n  num_envs: 2\n", r"unknown key 'trian' \(did you mean 'train'\?\)"),
    ("ppo: [1, 2]\n", "mapping"),
    ("ppo:\n  gamma: [0.9\n", "not valid YAML"),
])
def test_bad_config_names_file_and_key(tmp_path, text, match):
    f = tmp_path / "bad.yaml"
    f.write_text(text)
    with pytest.raises(ValueError, match=match) as ei:
        load_config(f)
    assert str(f) in str(ei.value)


def test_config_overrides_are_validated_and_missing_file_is_reported(tmp_path):
    p, _ = load_config(ppo={"minibatch_size": 64})
    assert p.minibatch_size == 64
    with pytest.raises(ValueError, match="minibatch_size"):
        load_config(ppo={"minibatch_size": -1})
    with pytest.raises(ValueError, match="cannot read"):
        load_config(tmp_path / "nope.yaml")


def test_a_config_file_overlays_the_packaged_one(tmp_path):
    """ppo_finetune.yaml lists three keys; everything else is ppo.yaml's (not a class default)."""
    from bimacppo_learning.ppo_config import DEFAULT_PATH
    finetune = DEFAULT_PATH.with_name("ppo_finetune.yaml")
    p, t = load_config(finetune)
    base_p, base_t = load_config()
    assert (p.actor_lr, p.entropy_coef, p.target_kl) == (1e-4, 0.001, 0.02)
    assert p == dataclasses.replace(base_p, actor_lr=1e-4, entropy_coef=0.001, target_kl=0.02) and t == base_t
    assert PPOConfig() == base_p and TrainConfig() == base_t     # the class's defaults are the packaged file
    f = tmp_path / "mine.yaml"
    f.write_text("train:\n  num_envs: 4\n")
    p, t = load_config(f, train={"batch_workers": 4})           # the file, then the overrides
    assert (t.num_envs, t.batch_workers, t.rollout_steps) == (4, 4, base_t.rollout_steps)
    # never more worker processes than envs: --num-envs 1 needs no second setting
    assert load_config(f, train={"batch_workers": 5})[1].workers == 4
    assert load_config(train={"num_envs": 1})[1].workers == 1


def test_saved_config_round_trips_and_older_dicts_take_packaged_defaults():
    from bimacppo_learning.ppo_config import config_from_dict, config_hash, config_to_dict
    p, t = load_config(ppo={"minibatch_size": 64}, train={"num_envs": 3})
    d = config_to_dict(p, t)
    assert config_from_dict(d) == (p, t)
    assert config_from_dict({"ppo": d["ppo"]}) == (p, None)
    old = {"ppo": dict(d["ppo"]), "train": dict(d["train"])}
    del old["train"]["batch_workers"], old["train"]["update_threads"], old["ppo"]["target_kl"]
    assert config_from_dict(old) == (p, t)
    assert config_hash(p) == config_hash(config_from_dict(d)[0]) != config_hash(PPOConfig())
    with pytest.raises(ValueError, match=r"ckpt\.pt: unknown key 'ppo\.gama'"):
        config_from_dict({"ppo": {"gama": 0.9}}, source="ckpt.pt")


def test_direct_construction_and_replace_are_validated():
    with pytest.raises(ValueError, match=r"PPOConfig: key 'gamma' must be in"):
        PPOConfig(gamma=2.0)
    with pytest.raises(ValueError, match="batch_workers"):
        dataclasses.replace(TrainConfig(), batch_workers=0)
    assert PPOConfig(hidden_sizes=[64, 64]).hidden_sizes == (64, 64)


def test_widened_inputs_keep_the_agents_actions_and_values_whatever_the_new_inputs_read():
    """ppo.widen_inputs: old inputs keep their weights and normaliser entries at their new
    places, new inputs start at zero weight, so the widened agent's logits and values are the
    original's for any value of the new inputs; bad column maps are refused."""
    import torch

    from bimacppo_learning.ppo import PPO, widen_inputs
    from bimacppo_learning.ppo_config import PPOConfig

    agent = PPO(5, [3, 2], PPOConfig(), seed=3)
    rng = np.random.default_rng(0)
    agent.obs_rms.update(rng.normal(2.0, 3.0, size=(64, 5)))
    wide = widen_inputs(agent, [0, 1, -1, 2, 3, 4, -1])
    assert wide.obs_dim == 7
    assert np.array_equal(wide.obs_rms.mean[[0, 1, 3, 4, 5]], agent.obs_rms.mean)
    assert wide.obs_rms.mean[2] == 0.0 and wide.obs_rms.var[6] == 1.0 and wide.obs_rms.count == 64
    obs = rng.normal(size=(10, 5)).astype(np.float32)
    for extra in (np.zeros((10, 2)), rng.normal(0.0, 50.0, size=(10, 2))):
        w_obs = np.concatenate([obs[:, :2], extra[:, :1], obs[:, 2:], extra[:, 1:]], axis=1).astype(np.float32)
        with torch.no_grad():
            a = agent.actor(torch.from_numpy(agent.normalize_obs(obs)))
            b = wide.actor(torch.from_numpy(wide.normalize_obs(w_obs)))
            va = agent.critic(torch.from_numpy(agent.normalize_obs(obs)))
            vb = wide.critic(torch.from_numpy(wide.normalize_obs(w_obs)))
        assert torch.allclose(a, b, atol=1e-6) and torch.allclose(va, vb, atol=1e-6)
    for bad in ([0, 1, 2, 3], [0, 1, 2, 3, 3], [0, 1, 2, 3, 5], [0, 1, 2, 3, 4, -2]):
        with pytest.raises(ValueError, match="columns"):
            widen_inputs(agent, bad)


def test_linear_lr_schedule_falls_to_the_final_fraction_and_constant_stays():
    p, _ = load_config()
    assert p.lr_schedule == "constant" and p.lr_fraction(0.7) == 1.0          # the paper's single rate
    lin = dataclasses.replace(p, lr_schedule="linear", lr_final_fraction=0.1)
    assert [lin.lr_fraction(x) for x in (0.0, 0.5, 1.0, 1.7)] == pytest.approx([1.0, 0.55, 0.1, 0.1])
    agent = PPO(4, NVEC, lin, seed=0)
    agent.set_lr_fraction(lin.lr_fraction(0.5))
    assert agent.actor_opt.param_groups[0]["lr"] == pytest.approx(0.55 * lin.actor_lr)
    assert agent.critic_opt.param_groups[0]["lr"] == pytest.approx(0.55 * lin.critic_lr)
    with pytest.raises(ValueError, match=r"in \[0, 1\]"):
        agent.set_lr_fraction(1.5)
    with pytest.raises(ValueError, match="lr_schedule"):
        dataclasses.replace(p, lr_schedule="cosine")


def test_linear_entropy_schedule_lowers_the_bonus_the_update_uses():
    p, _ = load_config()
    assert p.entropy_schedule == "constant" and p.entropy_coef_at(0.9) == p.entropy_coef
    lin = dataclasses.replace(p, entropy_schedule="linear", entropy_final_fraction=0.0, minibatch_size=64, epochs=2)
    assert [lin.entropy_coef_at(x) for x in (0.0, 0.25, 1.0, 2.0)] == pytest.approx(
        [p.entropy_coef, 0.75 * p.entropy_coef, 0.0, 0.0])
    agent = PPO(4, NVEC, lin, seed=3)
    agent.set_progress(0.5)
    assert agent.entropy_coef == pytest.approx(0.5 * p.entropy_coef)
    assert agent.actor_opt.param_groups[0]["lr"] == pytest.approx(lin.actor_lr)    # the rates keep their own schedule
    # zero advantages: only the entropy bonus moves the actor, so at the schedule's end it stays put
    obs = np.random.default_rng(0).normal(size=(128, 4)).astype(np.float32)
    acts, logp, _ = agent.act(obs)
    zero = np.zeros(128, np.float32)
    before = [t.clone() for t in agent.actor.state_dict().values()]
    agent.set_progress(1.0)
    agent.update(obs, acts, logp, zero, zero)
    assert all(torch.equal(a, b) for a, b in zip(before, agent.actor.state_dict().values()))
    agent.set_progress(0.0)
    ent0 = float(agent.dist(torch.as_tensor(obs)).entropy().mean())
    agent.update(obs, acts, logp, zero, zero)
    assert float(agent.dist(torch.as_tensor(obs)).entropy().mean()) > ent0
    with pytest.raises(ValueError, match="entropy_schedule"):
        dataclasses.replace(p, entropy_schedule="cosine")
    with pytest.raises(ValueError, match="entropy_final_fraction"):
        dataclasses.replace(p, entropy_final_fraction=1.5)


def test_a_zero_learning_rate_leaves_the_networks_as_they_were():
    """What the schedule's last updates rely on: the rate is the optimisers' real step size."""
    agent = PPO(4, NVEC, PPOConfig(minibatch_size=64, epochs=2), seed=3)
    obs = np.random.default_rng(0).normal(size=(128, 4)).astype(np.float32)
    before = [t.clone() for t in agent.actor.state_dict().values()]
    acts, logp, _ = agent.act(obs)
    agent.set_lr_fraction(0.0)
    agent.update(obs, acts, logp, np.where(acts[:, 0] == 2, 1.0, -1.0).astype(np.float32), np.zeros(128, np.float32))
    assert all(torch.equal(a, b) for a, b in zip(before, agent.actor.state_dict().values()))
    agent.set_lr_fraction(1.0)
    agent.update(obs, acts, logp, np.where(acts[:, 0] == 2, 1.0, -1.0).astype(np.float32), np.zeros(128, np.float32))
    assert not all(torch.equal(a, b) for a, b in zip(before, agent.actor.state_dict().values()))


def test_an_update_without_the_actor_fits_the_critic_and_leaves_the_actor_and_its_moments():
    """fit_actor=False (critic_warmup_updates): the actor's weights and Adam moments are those
    of before, the critic moves towards the returns, and the stats still report the actor's loss."""
    agent = PPO(4, NVEC, PPOConfig(minibatch_size=64, epochs=3), seed=3)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(128, 4)).astype(np.float32)
    ret = (2.0 * obs[:, 0] + 1.0).astype(np.float32)
    acts, logp, _ = agent.act(obs)
    adv = np.where(acts[:, 0] == 2, 1.0, -1.0).astype(np.float32)
    agent.update(obs, acts, logp, adv, ret)            # the actor has moments now
    actor = [t.clone() for t in agent.actor.state_dict().values()]
    moments = {k: v.clone() for st in agent.actor_opt.state.values() for k, v in st.items() if torch.is_tensor(v)}
    critic = [t.clone() for t in agent.critic.state_dict().values()]
    mse = lambda: float(((agent.value(obs) - ret) ** 2).mean())  # noqa: E731
    before = mse()
    acts, logp, _ = agent.act(obs)
    stats = agent.update(obs, acts, logp, adv, ret, fit_actor=False)
    assert all(torch.equal(a, b) for a, b in zip(actor, agent.actor.state_dict().values()))
    after_moments = {k: v for st in agent.actor_opt.state.values() for k, v in st.items() if torch.is_tensor(v)}
    assert all(torch.equal(moments[k], after_moments[k]) for k in moments)
    assert not all(torch.equal(a, b) for a, b in zip(critic, agent.critic.state_dict().values()))
    assert mse() < before
    assert stats["actor_fitted"] == 0.0 and stats["actor_grad_norm"] == 0.0 and np.isfinite(stats["policy_loss"])
    assert stats["approx_kl"] == pytest.approx(0.0, abs=1e-6)
    assert agent.update(obs, acts, logp, adv, ret)["actor_fitted"] == 1.0
    assert not all(torch.equal(a, b) for a, b in zip(actor, agent.actor.state_dict().values()))


def test_an_agent_adopts_a_fine_tunes_config_but_not_another_network():
    src = PPO(4, NVEC, PPOConfig(minibatch_size=64, epochs=2), seed=3)
    weights = [t.clone() for t in src.actor.state_dict().values()]
    tuned = dataclasses.replace(src.cfg, entropy_coef=0.03, actor_lr=1e-4, adam_eps=1e-6, obs_clip=5.0)
    src.adopt_config(tuned)
    assert src.cfg is tuned
    assert src.actor_opt.param_groups[0]["lr"] == 1e-4 and src.actor_opt.param_groups[0]["eps"] == 1e-6
    assert src.obs_rms.clip == 5.0
    assert all(torch.equal(a, b) for a, b in zip(weights, src.actor.state_dict().values()))
    with pytest.raises(ValueError, match=r"hidden_sizes \(\(256, 128\) -> \(64,\)\), activation"):
        src.adopt_config(dataclasses.replace(tuned, hidden_sizes=(64,), activation="relu"))
    assert src.cfg is tuned


def test_a_head_prior_fixes_one_heads_odds_in_every_state_and_leaves_the_rest():
    """ppo.set_head_prior: the head's logits no longer depend on the input and give exactly the
    prior; the other heads' logits, the critic and the optimiser's moments of other rows are
    untouched, the head's own moments restart at zero; bad priors are refused."""
    import torch

    from bimacppo_learning.ppo import PPO, set_head_prior
    from bimacppo_learning.ppo_config import PPOConfig

    agent = PPO(6, [5, 5, 3], PPOConfig(init_gain_policy=1.0), seed=2)
    obs = torch.from_numpy(np.random.default_rng(1).normal(0.0, 2.0, size=(32, 6)).astype(np.float32))
    loss = agent.actor(obs).pow(2).sum()            # one optimiser step gives every row moments
    agent.actor_opt.zero_grad()
    loss.backward()
    agent.actor_opt.step()
    with torch.no_grad():
        before, value = agent.actor(obs).clone(), agent.critic(obs).clone()
    out = agent.actor[-1]
    moments = {k: v.clone() for k, v in agent.actor_opt.state[out.weight].items() if torch.is_tensor(v) and v.ndim}
    set_head_prior(agent, 2, [0.1, 0.8, 0.1])
    with torch.no_grad():
        after = agent.actor(obs)
        probs = agent.dist(obs).log_probs[2].exp()
    assert torch.allclose(probs, torch.tensor([0.1, 0.8, 0.1]).expand(32, 3), atol=1e-6)
    assert torch.equal(after[:, :10], before[:, :10])
    assert torch.equal(agent.critic(obs).detach(), value)
    for k, m in moments.items():
        now = agent.actor_opt.state[out.weight][k]
        assert torch.equal(now[:10], m[:10]) and not now[10:].any() and m[10:].any()
    for head, probs_, match in ((3, [0.5, 0.5], "head"), (2, [0.5, 0.5], "3 actions"), (2, [0.5, 0.6, -0.1], "positive"),
                                (2, [0.2, 0.2, 0.2], "sum to 1"), (0, [0.0, 0.25, 0.25, 0.25, 0.25], "positive")):
        with pytest.raises(ValueError, match=match):
            set_head_prior(agent, head, probs_)


def test_adam_is_the_fused_kernel_with_the_per_tensor_rule_and_stays_fused_after_a_load():
    """The optimisers are torch's fused Adam; one update moves the weights as the per-tensor Adam
    does (to rounding), and a state saved by a per-tensor Adam loads into a fused one."""
    cfg = PPOConfig()
    rng = np.random.default_rng(0)
    n = 256
    obs = rng.standard_normal((n, 16)).astype(np.float32)
    act = np.stack([rng.integers(0, k, n) for k in NVEC], 1)
    lp = np.full(n, -3.5, np.float32)
    adv = rng.standard_normal(n).astype(np.float32)
    ret = rng.standard_normal(n).astype(np.float32)
    fused, plain = PPO(16, NVEC, cfg, seed=1), PPO(16, NVEC, cfg, seed=1)
    for opt in (fused.actor_opt, fused.critic_opt):
        assert all(g["fused"] for g in opt.param_groups)
    plain.actor_opt = torch.optim.Adam(plain.actor.parameters(), lr=cfg.actor_lr, eps=cfg.adam_eps)
    plain.critic_opt = torch.optim.Adam(plain.critic.parameters(), lr=cfg.critic_lr, eps=cfg.adam_eps)
    before = [p.detach().clone() for p in fused.actor.parameters()]
    fused.update(obs, act, lp, adv, ret)
    plain.update(obs, act, lp, adv, ret)
    moved = max(float((p - b).abs().max()) for p, b in zip(fused.actor.parameters(), before))
    gap = max(float((p - q).abs().max()) for p, q in zip(fused.actor.parameters(), plain.actor.parameters()))
    assert moved > 1e-4 and gap < 1e-3 * moved
    buf = io.BytesIO()           # as a checkpoint file: the loaded state shares no tensor with the source
    torch.save(plain.state_dict(), buf)
    buf.seek(0)
    loaded = PPO(16, NVEC, cfg, seed=2)
    loaded.load_state_dict(torch.load(buf, weights_only=True))
    for opt, src in ((loaded.actor_opt, plain.actor_opt), (loaded.critic_opt, plain.critic_opt)):
        assert all(g["fused"] for g in opt.param_groups)
        assert all(torch.equal(opt.state[p]["exp_avg"], src.state[q]["exp_avg"])
                   for p, q in zip(opt.param_groups[0]["params"], src.param_groups[0]["params"]))
    loaded.update(obs, act, lp, adv, ret)
    plain.update(obs, act, lp, adv, ret)
    gap = max(float((p - q).abs().max()) for p, q in zip(loaded.actor.parameters(), plain.actor.parameters()))
    assert gap < 1e-3 * moved


def _rollout(n=300, dim=16, seed=0):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((n, dim)).astype(np.float32), np.stack([rng.integers(0, k, n) for k in NVEC], 1),
            np.full(n, -3.5, np.float32), rng.standard_normal(n).astype(np.float32),
            rng.standard_normal(n).astype(np.float32))


def _interleaved_update(agent, obs, act, lp, adv, ret):
    """PPO's update written the textbook way, actor and critic step by step on each minibatch:
    the reference the epoch-wise fit must reproduce bit for bit."""
    c = agent.cfg
    O, A, LP = torch.as_tensor(obs), torch.as_tensor(act, dtype=torch.long), torch.as_tensor(lp)
    ADV, RET = torch.as_tensor(adv), torch.as_tensor(ret)
    n = O.shape[0]
    for _ in range(c.epochs):
        perm = torch.randperm(n, generator=agent.gen)
        for s in range(0, n, c.minibatch_size):
            idx = perm[s:s + c.minibatch_size]
            if idx.numel() < 2:
                continue
            a = ADV[idx]
            a = (a - a.mean()) / (a.std() + 1e-8)
            d = agent.dist(O[idx])
            pl, _, _ = clipped_surrogate(d.log_prob(A[idx]), LP[idx], a, c.clip_eps)
            agent.actor_opt.zero_grad(set_to_none=True)
            (pl - agent.entropy_coef * d.entropy().mean()).backward()
            torch.nn.utils.clip_grad_norm_(agent.actor.parameters(), c.max_grad_norm)
            agent.actor_opt.step()
            vl = 0.5 * (agent.critic(O[idx]).squeeze(-1) - RET[idx]).pow(2).mean()
            agent.critic_opt.zero_grad(set_to_none=True)
            vl.backward()
            torch.nn.utils.clip_grad_norm_(agent.critic.parameters(), c.max_grad_norm)
            agent.critic_opt.step()


def _same_state(a, b):
    sa, sb = a.state_dict(), b.state_dict()
    for net in ("actor", "critic"):
        assert all(torch.equal(sa[net][k], sb[net][k]) for k in sa[net]), net
    for opt in ("actor_opt", "critic_opt"):
        for pid, st in sa[opt]["state"].items():
            assert all(torch.equal(v, sb[opt]["state"][pid][k]) for k, v in st.items()), opt


@pytest.mark.parametrize("target_kl", [None, 0.002])
def test_the_critic_fitted_on_its_own_thread_gives_the_interleaved_update_bit_for_bit(target_kl, monkeypatch):
    """The update fits actor and critic epoch by epoch, the critic on a second thread when asked:
    the weights, optimiser moments and statistics equal those of one thread, and the weights equal
    the textbook interleaved loop's (the networks share nothing). With target_kl, both threads
    stop after the same epoch."""
    import threading

    cfg = dataclasses.replace(PPOConfig(), minibatch_size=64, epochs=6, target_kl=target_kl)
    data = _rollout(n=300)      # 4 full minibatches and a 44-sample tail
    one, two, ref = (PPO(16, NVEC, cfg, seed=4) for _ in range(3))
    threads = []
    fit = PPO._fit_critic

    def recording(self, *a):
        threads.append(threading.get_ident())
        return fit(self, *a)

    monkeypatch.setattr(PPO, "_fit_critic", recording)
    s1 = one.update(*data, critic_thread=False)
    assert set(threads) == {threading.get_ident()}
    threads.clear()
    s2 = two.update(*data, critic_thread=True)
    assert threading.get_ident() not in threads and len(threads) == s2["epochs"]
    monkeypatch.undo()
    assert s1 == pytest.approx(s2, nan_ok=True, rel=0, abs=0)
    _same_state(one, two)
    if target_kl is None:
        assert s2["epochs"] == 6 and s2["minibatch_steps"] == 30
        _interleaved_update(ref, *data)
        for net in ("actor", "critic"):
            assert all(torch.equal(p, q) for p, q in zip(getattr(ref, net).parameters(), getattr(two, net).parameters()))
    else:
        assert s2["early_stop"] == 1.0 and s2["epochs"] < 6


def test_a_critic_warm_up_on_the_critics_thread_leaves_the_actor_as_it_was():
    cfg = dataclasses.replace(PPOConfig(), minibatch_size=64, epochs=3)
    data = _rollout(n=256, seed=1)
    agent, serial = PPO(16, NVEC, cfg, seed=5), PPO(16, NVEC, cfg, seed=5)
    before = [p.detach().clone() for p in agent.actor.parameters()]
    stats = agent.update(*data, fit_actor=False, critic_thread=True)
    serial.update(*data, fit_actor=False, critic_thread=False)
    assert all(torch.equal(p, b) for p, b in zip(agent.actor.parameters(), before))
    assert stats["actor_fitted"] == 0.0 and stats["critic_grad_norm"] > 0.0
    _same_state(agent, serial)
