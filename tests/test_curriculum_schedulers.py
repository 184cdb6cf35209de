"""The shared scheduler interface: factory, baselines' sampling laws, resume, configs."""
import dataclasses
import json
import math

import numpy as np
import pytest

from bimacppo_curriculum import SCHEDULERS, BiMAB, BiMABConfig, make_scheduler, scheduler_from_state

TOTAL = 4000


def returns(seed):
    rng = np.random.default_rng(seed)
    return lambda i, j: float(rng.normal(8 * i - 3 * j, 6))


def play(s, n, ret):
    out = []
    for _ in range(n):
        i, j = s.sample()
        out.append((i, j))
        s.update(i, j, ret(i, j))
    return out


def within(freq, p, n, sigmas=4.5):
    """Every empirical frequency within `sigmas` binomial standard errors of its probability."""
    freq, p = np.asarray(freq, float), np.asarray(p, float)
    tol = sigmas * np.sqrt(np.maximum(p * (1 - p), 1e-12) / n) + 1e-12
    return np.all(np.abs(freq - p) <= tol), np.abs(freq - p) / tol


# ------------------------------------------------------------------ interface
@pytest.mark.parametrize("name", sorted(SCHEDULERS))
def test_interface_types_and_log_dict(name):
    s = make_scheduler(name, seed=0, total_episodes=TOTAL)
    i, j = s.sample()
    assert type(i) is int and type(j) is int and 0 <= i <= 3 and 0 <= j <= 2
    s.update(i, j, 12.5)
    p_c, p_a = s.probabilities()
    assert p_c.shape == (4,) and p_a.shape == (4, 3)
    assert p_c.sum() == pytest.approx(1.0) and np.allclose(p_a.sum(axis=1), 1.0)
    log = s.log_dict()
    assert all(isinstance(k, str) and type(v) is float and math.isfinite(v) for k, v in log.items())
    assert log["episodes"] == 1.0 and log["samples"] == 1.0 and log[f"count_{i}_{j}"] == 1.0
    assert sum(log[f"count_{c}"] for c in range(4)) == 1.0
    json.dumps(s.state_dict())   # JSON-serialisable


def test_seeds_make_sampling_reproducible_and_distinct():
    for name in SCHEDULERS:
        a = play(make_scheduler(name, seed=4, total_episodes=TOTAL), 300, returns(0))
        b = play(make_scheduler(name, seed=4, total_episodes=TOTAL), 300, returns(0))
        c = play(make_scheduler(name, seed=5, total_episodes=TOTAL), 300, returns(0))
        assert a == b, name
        assert a != c, name


def test_unknown_scheduler_and_missing_budget_are_clear_errors():
    with pytest.raises(ValueError, match="unknown scheduler 'bandit'"):
        make_scheduler("bandit")
    with pytest.raises(ValueError, match="total_episodes"):
        make_scheduler("manual", seed=0)
    with pytest.raises(ValueError, match="seed"):
        make_scheduler("random", seed=-1)


# ------------------------------------------------------------------ resume
@pytest.mark.parametrize("name", sorted(SCHEDULERS))
def test_state_dict_round_trip_reproduces_future_samples(name):
    cfg = {"sync_interval": 50} if name in ("bimab", "rd") else None
    a = make_scheduler(name, seed=7, total_episodes=TOTAL, config=cfg)
    play(a, 1237, returns(1))                      # mid-interval, mid-stage
    state = json.loads(json.dumps(a.state_dict()))
    b = make_scheduler(name, seed=123, total_episodes=TOTAL, config=cfg)   # different seed: state wins
    b.load_state_dict(state)
    c = scheduler_from_state(state)
    assert b.log_dict() == a.log_dict() == c.log_dict()
    ra, rb, rc = returns(2), returns(2), returns(2)
    assert play(a, 400, ra) == play(b, 400, rb) == play(c, 400, rc)
    assert a.log_dict() == b.log_dict()


def test_state_with_pending_draws_resumes_exactly():
    a = make_scheduler("bimab", seed=1, config={"sync_interval": 3})
    draws = [a.sample() for _ in range(5)]         # five episodes "in flight"
    state = json.loads(json.dumps(a.state_dict()))
    b = scheduler_from_state(state)
    for (i, j), r in zip(draws, (4.0, -2.0, 9.0, 1.0, -6.0)):
        a.update(i, j, r)
        b.update(i, j, r)
    np.testing.assert_array_equal(a.clusters.tw, b.clusters.tw)
    np.testing.assert_array_equal(a.arms.tw, b.arms.tw)
    assert a.sample() == b.sample()


def test_bad_states_are_rejected_without_side_effects():
    s = make_scheduler("bimab", seed=0, config={"sync_interval": 10})
    play(s, 30, returns(0))
    good = json.loads(json.dumps(s.state_dict()))
    fresh = make_scheduler("bimab", seed=0, config={"sync_interval": 10})
    before = fresh.log_dict()
    cases = {
        "scheduler": dict(good, scheduler="rd"),
        "config": dict(good, config=dict(good["config"], eta=0.3)),
        "arms": dict(good, arms={"w": [[1.0, 2.0]], "tw": good["arms"]["tw"]}),
        "rng": dict(good, rng={"bit_generator": "nope"}),
        "counts": dict(good, counts=[[1, 2, 3]]),
        "r_max": dict(good, rescaler={"r_max": -1.0, "r_min": 0.0}),
    }
    for key, bad in cases.items():
        with pytest.raises(ValueError, match=key):
            fresh.load_state_dict(bad)
        assert fresh.log_dict() == before, key
    del good["clusters"]
    with pytest.raises(ValueError, match="clusters"):
        fresh.load_state_dict(good)


def test_a_state_saved_before_a_config_key_existed_resumes():
    a = make_scheduler("bimab", seed=3, config={"sync_interval": 10})
    play(a, 30, returns(1))
    state = json.loads(json.dumps(a.state_dict()))
    del state["config"]["max_pending"]          # the key is newer than the state
    b = make_scheduler("bimab", seed=3, config={"sync_interval": 10})
    b.load_state_dict(state)
    assert b.n_updates == 30 and b.sample() == a.sample()
    other = make_scheduler("bimab", seed=3, config={"sync_interval": 10, "max_pending": a.config.max_pending + 1})
    with pytest.raises(ValueError, match=r"differs from this scheduler's config in \['max_pending'\]"):
        other.load_state_dict(state)             # the packaged default is not this scheduler's value
    with pytest.raises(ValueError, match=r"config.*\['sync_interval'\]"):
        make_scheduler("bimab", seed=3).load_state_dict(state)
    with pytest.raises(ValueError, match=r"state: key 'config'.*unknown key 'sync_intervall'"):
        b.load_state_dict(dict(state, config={"sync_intervall": 10}))


# ------------------------------------------------------------------ baselines' laws
def test_fixed_ppo_always_hardest_cluster_tasks_uniform():
    s = make_scheduler("fixed", seed=0)
    n = 9000
    draws = np.array(play(s, n, returns(0)))
    assert np.all(draws[:, 0] == 3)
    ok, z = within(np.bincount(draws[:, 1], minlength=3) / n, np.full(3, 1 / 3), n)
    assert ok, z


def test_random_cppo_is_uniform_over_all_scenarios():
    s = make_scheduler("random", seed=1)
    n = 24000
    draws = np.array(play(s, n, returns(0)))
    freq = np.bincount(draws[:, 0] * 3 + draws[:, 1], minlength=12) / n
    ok, z = within(freq, np.full(12, 1 / 12), n)
    assert ok, z


def test_manual_cppo_follows_its_stages_with_epsilon():
    s = make_scheduler("manual", seed=2, total_episodes=TOTAL)
    eps = s.config.epsilon
    draws = np.array(play(s, TOTAL + 500, returns(0)))
    q = TOTAL // 4
    for stage, n_sv in enumerate(s.config.stages):
        part = draws[stage * q:(stage + 1) * q]
        expect = np.full(4, eps / 4)
        expect[n_sv] += 1 - eps
        ok, z = within(np.bincount(part[:, 0], minlength=4) / q, expect, q)
        assert ok, (stage, z)
        ok, z = within(np.bincount(part[:, 1], minlength=3) / q, np.full(3, 1 / 3), q)
        assert ok, (stage, z)
    assert np.mean(draws[TOTAL:, 0] == 3) > 0.7         # past the budget: last stage stays
    # the stage boundary is exact, in episodes started
    t = make_scheduler("manual", seed=0, total_episodes=TOTAL)
    for k in range(q - 1):
        t.sample()
    assert t.log_dict()["stage"] == 0.0
    t.sample()
    assert t.log_dict()["stage"] == 1.0 and t.probabilities()[0].argmax() == 1


def test_rd_acppo_learns_clusters_only_and_keeps_tasks_uniform():
    s = make_scheduler("rd", seed=3, config={"sync_interval": 200, "alpha_c": 0.05})
    draws = np.array(play(s, 3000, lambda i, j: 30.0 if i == 2 else 1.0))
    p_c, p_a = s.probabilities()
    np.testing.assert_allclose(p_a, 1 / 3)
    assert p_c.argmax() == 2 and p_c[2] > 0.5 and p_c.min() >= 0.2 / 4 - 1e-15
    ok, z = within(np.bincount(draws[:, 1], minlength=3) / 3000, np.full(3, 1 / 3), 3000)
    assert ok, z
    assert not any(k.startswith("arm_weight") for k in s.log_dict())


def test_bimab_draws_follow_its_current_law():
    s = make_scheduler("bimab", seed=4, config={"sync_interval": 300, "alpha_c": 0.05, "alpha_a": 0.05})
    play(s, 300, lambda i, j: 20.0 * (i == 1) + 5.0 * (j == 2))   # one sync: law is now skewed
    p_c, p_a = s.probabilities()
    assert p_c[1] > 0.5
    n = 299                                                        # stay inside one sync interval
    draws = np.array(play(s, n, lambda i, j: 0.0))
    ok, z = within(np.bincount(draws[:, 0], minlength=4) / n, p_c, n)
    assert ok, z


# ------------------------------------------------------------------ configs
def test_packaged_configs_load():
    c = BiMABConfig.load()
    assert (c.eta, c.initial_weight, c.sync_interval, c.n_sv_max) == (0.2, 1.0, 1000, 3)


def test_broken_config_files_name_the_key(tmp_path):
    text = (BiMABConfig.load.__func__.__globals__["CONFIG_DIR"] / "bimab.yaml").read_text()
    cases = {
        "eta": text.replace("eta: 0.2", "eta: 1.5"),
        "sync_interval": text.replace("sync_interval: 1000", "sync_interval: 10.5"),
        "alpha_c": text.replace("alpha_c: 0.01", "alpha_c: fast"),
        "k1": text.replace("k1: 1.0", "k1: 0.05"),
        "gamma": text + "gamma: 0.9\n",
        "k0": "k0: 2.0\n",       # an overlay of one key that breaks k1 >= k0: still named by this file
    }
    for key, body in cases.items():
        p = tmp_path / f"{key}.yaml"
        p.write_text(body)
        with pytest.raises(ValueError, match=key) as exc:
            make_scheduler("bimab", config=str(p))
        assert str(p) in str(exc.value)
    bad = tmp_path / "bad.yaml"
    bad.write_text("eta: [0.2\n")
    with pytest.raises(ValueError, match="not valid YAML"):
        make_scheduler("bimab", config=bad)
    with pytest.raises(ValueError, match="cannot read"):
        make_scheduler("bimab", config=tmp_path / "missing.yaml")


def test_a_config_file_overlays_the_packaged_one(tmp_path):
    """A user's file lists only what it changes; the rest is the packaged file's, and what it
    misspells is refused with the closest key suggested."""
    p = tmp_path / "fast_sync.yaml"
    p.write_text("# only the sync period differs\nsync_interval: 50\n")
    s = make_scheduler("bimab", config=p)
    assert s.config == dataclasses.replace(BiMABConfig(), sync_interval=50)
    assert BiMABConfig().beta_a == 0.001                      # the packaged value, written once
    p.write_text("sync_intervall: 50\n")
    with pytest.raises(ValueError, match=r"unknown key 'sync_intervall' \(did you mean 'sync_interval'\?\)"):
        make_scheduler("bimab", config=p)


def test_a_saved_config_lacking_a_newer_key_takes_the_packaged_default():
    saved = BiMABConfig().to_dict()
    del saved["max_pending"]
    assert BiMABConfig.from_dict(saved, source="old state") == BiMABConfig()
    with pytest.raises(ValueError, match=r"old state: key 'max_pending' must be >= 0"):
        BiMABConfig.from_dict({**saved, "max_pending": -1}, source="old state")


def test_configs_are_frozen_and_checked_on_replace():
    c = BiMABConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.eta = 0.5
    with pytest.raises(ValueError, match="eta"):
        dataclasses.replace(c, eta=2.0)


def test_override_dicts_are_validated():
    with pytest.raises(ValueError, match="sync_intervall"):
        make_scheduler("bimab", config={"sync_intervall": 10})
    with pytest.raises(ValueError, match="eta"):
        make_scheduler("rd", config={"eta": 0.0})
    with pytest.raises(ValueError, match="stages"):
        make_scheduler("manual", total_episodes=10, config={"stages": [0, 4]})
    with pytest.raises(ValueError, match="epsilon"):
        make_scheduler("manual", total_episodes=10, config={"epsilon": True})
    s = make_scheduler("bimab", config={"sync_interval": 10})
    assert isinstance(s, BiMAB) and s.config.sync_interval == 10
