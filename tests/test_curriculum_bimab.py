"""BiMAB (paper Algorithm 1, eq. (11)-(17)): probabilities, rescaling, sync, stability."""
import math
import pathlib

import numpy as np
import pytest

from bimacppo_curriculum import BiMAB, BiMABConfig, RewardRescaler, make_scheduler
from bimacppo_curriculum.bandit import Exp3SLevel


def cfg(**kw):
    base = dict(n_sv_max=3, eta=0.2, initial_weight=1.0, sync_interval=1000, k0=0.1, k1=1.0, alpha_md=0.5,
                alpha_c=0.01, alpha_a=0.01, beta_c=0.001, beta_a=0.001, max_pending=4096)
    base.update(kw)
    return base


# ------------------------------------------------------------------ eq. (11)
def test_initial_probabilities_are_uniform():
    s = make_scheduler("bimab", seed=0)
    p_c, p_a = s.probabilities()
    assert p_c.shape == (4,) and p_a.shape == (4, 3)
    np.testing.assert_allclose(p_c, 0.25)
    np.testing.assert_allclose(p_a, 1 / 3)


def test_probabilities_sum_to_one_and_respect_the_eta_floor():
    s = make_scheduler("bimab", seed=3, config=cfg(sync_interval=7, alpha_c=0.5, alpha_a=0.5))
    rng = np.random.default_rng(0)
    for _ in range(400):
        i, j = s.sample()
        # reward the hardest scenario hugely so the softmax saturates
        s.update(i, j, 100.0 if (i, j) == (3, 0) else float(rng.normal()))
    p_c, p_a = s.probabilities()
    assert p_c.sum() == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(p_a.sum(axis=1), 1.0, atol=1e-12)
    assert p_c.min() >= 0.2 / 4 - 1e-15
    assert p_a.min() >= 0.2 / 3 - 1e-15
    # the law did move: the rewarded scenario dominates its level
    assert p_c.argmax() == 3 and p_c[3] > 0.5
    assert p_a[3].argmax() == 0 and p_a[3, 0] > 0.5


def test_arm_softmax_runs_over_the_arms_of_its_own_cluster():
    lvl = Exp3SLevel(rows=4, k=3, w0=1.0, eta=0.2, alpha=1.0, beta=0.0)
    lvl.w[2] = [5.0, 0.0, 0.0]           # only cluster 2's arms differ
    p = lvl.probs()
    np.testing.assert_allclose(p[[0, 1, 3]], 1 / 3)
    e = np.exp([5.0, 0.0, 0.0])
    np.testing.assert_allclose(p[2], 0.8 * e / e.sum() + 0.2 / 3)


# ------------------------------------------------------------------ eq. (14)-(15)
def test_rescaling_matches_hand_worked_numbers():
    r = RewardRescaler(k0=0.1, k1=1.0, alpha_md=0.5)
    # ep 1: r = 10 -> R_max = R_min = 10; r_md = 10; 2*(10 - 1)/(10 - 1) - 1 = 1
    assert r.observe(10.0) == pytest.approx(1.0)
    # ep 2: r = -4 -> r_md = 0.5*4 = 2; R_max 10, R_min 4: 2*(2 - 0.4)/(10 - 0.4) - 1 = -2/3
    assert r.observe(-4.0) == pytest.approx(-2.0 / 3.0)
    # ep 3: r = 2 -> R_min 2: 2*(2 - 0.2)/(10 - 0.2) - 1
    assert r.observe(2.0) == pytest.approx(3.6 / 9.8 - 1.0)
    # a big failure is mirrored: r = -30 -> R_max 30, r_md 15: 2*(15 - 0.2)/(30 - 0.2) - 1
    assert r.observe(-30.0) == pytest.approx(29.6 / 29.8 - 1.0)
    assert (r.r_max, r.r_min) == (30.0, 2.0)


def test_rescaling_can_leave_unit_interval_when_constants_allow_it():
    # alpha_md > 1 puts a negative return's r_md above R_max: r_norm > 1 (documented)
    r = RewardRescaler(k0=0.1, k1=1.0, alpha_md=2.0)
    r.observe(1.0)
    assert r.observe(-10.0) > 1.0


def test_rescaling_is_scale_free_and_degenerate_history_gives_zero():
    a, b = RewardRescaler(0.1, 1.0, 0.5), RewardRescaler(0.1, 1.0, 0.5)
    for x in (3.0, -7.0, 0.5, 12.0, -1.0):
        assert a.observe(x) == pytest.approx(b.observe(x * 1e290), rel=1e-12)
    flat = RewardRescaler(k0=1.0, k1=1.0, alpha_md=0.5)
    assert flat.observe(5.0) == 0.0          # R_max == R_min with k0 == k1: no information
    assert RewardRescaler(0.1, 1.0, 0.5).observe(0.0) == 0.0


def test_first_update_moves_the_target_weights_as_eq16_says():
    s = BiMAB(config=cfg(), seed=0)
    s.update(2, 1, 10.0)                     # r_norm = 1 (first episode, see above)
    # cluster: +alpha_c * 1 / 0.25 = 0.04 on cluster 2, then re-centred to mean 1
    np.testing.assert_allclose(s.clusters.tw[0], [0.99, 0.99, 1.03, 0.99])
    # arm: +alpha_a * 1 / (1/3) = 0.03 on arm 1 of cluster 2 only
    np.testing.assert_allclose(s.arms.tw[2], [0.99, 1.02, 0.99])
    np.testing.assert_allclose(s.arms.tw[[0, 1, 3]], 1.0)
    # the sampling copy has not moved (no sync yet)
    np.testing.assert_allclose(s.clusters.w, 1.0)
    np.testing.assert_allclose(s.arms.w, 1.0)


def test_importance_weight_uses_the_probability_the_episode_was_drawn_with():
    s = BiMAB(config=cfg(sync_interval=1, alpha_c=1.0), seed=0)
    s.update(0, 0, 10.0)                     # sync after every episode: law no longer uniform
    i, j = s.sample()
    p_drawn = s.probabilities()[0][i]
    s.update(3 - i if i != 3 else 0, 0, 5.0)  # another scenario's return arrives first: syncs again
    assert s.probabilities()[0][i] != pytest.approx(p_drawn)
    before = s.clusters.tw[0].copy()
    r_norm = s.rescaler.normalise(5.0)
    s.update(i, j, 5.0)
    # recompute the re-centred step with the *drawn* probability
    step = np.zeros(4)
    step[i] = r_norm / p_drawn
    expected = before + step - step.mean()
    np.testing.assert_allclose(s.clusters.tw[0], expected, rtol=1e-12, atol=1e-12)


def test_matches_a_literal_implementation_of_eq16_and_eq17():
    """Our re-centred weights differ from the paper's raw ones by a per-level constant only."""
    c = cfg(sync_interval=25, alpha_c=0.05, alpha_a=0.05, beta_c=0.002, beta_a=0.003)
    s = BiMAB(config=c, seed=11)
    wc, wa = np.ones(4), np.ones((4, 3))     # literal sampling weights
    twc, twa = np.ones(4), np.ones((4, 3))   # literal target weights
    rs = RewardRescaler(c["k0"], c["k1"], c["alpha_md"])
    rng = np.random.default_rng(5)

    def law(w):
        e = np.exp(w - w.max(axis=-1, keepdims=True))
        return 0.8 * e / e.sum(axis=-1, keepdims=True) + 0.2 / w.shape[-1]

    for t in range(1, 301):
        i, j = s.sample()
        pc, pa = law(wc), law(wa)
        np.testing.assert_allclose(s.probabilities()[0], pc, rtol=1e-9)
        np.testing.assert_allclose(s.probabilities()[1], pa, rtol=1e-9)
        r = float(rng.normal(3 * i - 4, 5))
        rn = rs.observe(r)
        Wc, Wa = twc.sum(), twa.sum(axis=1, keepdims=True)
        twc = twc + c["beta_c"] * Wc
        twc[i] += c["alpha_c"] * rn / pc[i]
        twa = twa + c["beta_a"] * Wa
        twa[i, j] += c["alpha_a"] * rn / pa[i, j]
        if t % c["sync_interval"] == 0:
            wc, wa = twc.copy(), twa.copy()
        s.update(i, j, r)
        dc = twc - s.clusters.tw[0]
        da = twa - s.arms.tw
        assert np.ptp(dc) < 1e-9 and np.all(np.ptp(da, axis=1) < 1e-9)
    assert abs(twc.mean() - 1.0) > 1.0   # the literal weights drift as a whole (beta term); ours stay centred
    np.testing.assert_allclose(s.clusters.tw.mean(), 1.0)


# ------------------------------------------------------------------ eq. (17): sync
def test_sampling_law_is_constant_between_syncs_and_changes_exactly_at_sync():
    n = 40
    s = make_scheduler("bimab", seed=2, config=cfg(sync_interval=n, alpha_c=0.05, alpha_a=0.05))
    rng = np.random.default_rng(1)
    laws = []
    for t in range(1, 4 * n + 1):
        i, j = s.sample()
        s.update(i, j, float(rng.normal(10 * i, 3)))
        pc, pa = s.probabilities()
        laws.append(np.concatenate([pc, pa.ravel()]))
        if t % n == 0:   # right after a sync the sampling law is the target's
            tc, ta = s.target_probabilities()
            np.testing.assert_array_equal(pc, tc)
            np.testing.assert_array_equal(pa, ta)
    laws = np.array(laws)
    init = np.concatenate([np.full(4, 0.25), np.full(12, 1 / 3)])
    np.testing.assert_allclose(laws[: n - 1], np.broadcast_to(init, (n - 1, 16)))
    for k in range(4):
        block = laws[k * n + n - 1: (k + 1) * n + n - 1]   # from the sync after episode (k+1)n
        assert np.all(block == block[0])
        prev = laws[k * n + n - 2]
        assert np.abs(block[0] - prev).max() > 1e-6, f"law did not change at sync {k + 1}"
    assert s.log_dict()["syncs"] == 4


# ------------------------------------------------------------------ numerical stability
def test_a_million_updates_with_huge_returns_stay_finite():
    s = make_scheduler("bimab", seed=0, config=cfg(sync_interval=1000, beta_c=0.5, beta_a=0.5, alpha_c=1.0, alpha_a=1.0))
    huge = (1e300, -1e300, 1.7e308, -1.7e308, 1e-300, 0.0, 3.0, -5e307)
    for t in range(1_000_000):
        s.update(t % 4, (t // 4) % 3, huge[t % len(huge)])
    pc, pa = s.probabilities()
    tc, ta = s.target_probabilities()
    for a in (pc, pa, tc, ta, s.clusters.w, s.clusters.tw, s.arms.w, s.arms.tw):
        assert np.all(np.isfinite(a))
    assert pc.sum() == pytest.approx(1.0) and np.allclose(pa.sum(axis=1), 1.0)
    assert all(math.isfinite(v) for v in s.log_dict().values())


def test_non_finite_or_bad_inputs_raise():
    s = make_scheduler("bimab", seed=0)
    for bad in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(ValueError, match="finite"):
            s.update(0, 0, bad)
    with pytest.raises(ValueError, match="real number"):
        s.update(0, 0, "3.0")
    with pytest.raises(ValueError, match="cluster"):
        s.update(4, 0, 1.0)
    with pytest.raises(ValueError, match="arm"):
        s.update(0, 3, 1.0)
    with pytest.raises(ValueError, match="integer"):
        s.update(0.0, 1, 1.0)
    assert s.n_updates == 0   # nothing was counted


@pytest.mark.parametrize("name", ["bimab", "rd"])
def test_budget_scaling_gives_every_run_min_syncs_and_a_moving_law(name):
    from bimacppo_curriculum.bandit import budget_scaling
    c = make_scheduler(name, seed=0).config
    assert (c.min_syncs, c.step_budget) == (10, 5000)
    assert budget_scaling(c, 1000) == (100, 5.0) and budget_scaling(c, 5000) == (500, 1.0)
    assert budget_scaling(c, 50_000) == (c.sync_interval, 0.1)       # never sparser than N_BiMAB
    assert budget_scaling(c, None) == (c.sync_interval, 1.0)
    off = make_scheduler(name, seed=0, total_episodes=1000, config={"min_syncs": None, "step_budget": None})
    assert off.sync_interval == c.sync_interval and off.alpha_scale == 1.0   # the paper's fixed values
    s = make_scheduler(name, seed=0, total_episodes=1000)
    rng = np.random.default_rng(0)
    laws = []
    for t in range(1, 1001):
        i, j = s.sample()
        s.update(i, j, float(10.0 * i - 5.0 + rng.normal()))   # harder clusters pay more: a law worth moving
        if t % 100 == 99 or t == 100:
            laws.append(s.probabilities()[0].copy())
    assert s.n_syncs == 10
    np.testing.assert_allclose(laws[0], 0.25)                     # before the first sync: uniform
    assert np.abs(laws[1] - 0.25).max() > 0.05                    # the first sync (episode 100) moved it
    assert np.argmax(s.probabilities()[0]) == 3


def test_wider_mix_overlay_changes_only_eta_and_doubles_the_floors():
    """studies/config/curriculum_eta04.yaml (variant 12) is an overlay: eta alone differs from the
    packaged bimab.yaml, and under a saturating reward the law sits on its floors eta/K."""
    overlay = pathlib.Path(__file__).resolve().parent.parent / "studies" / "config" / "curriculum_eta04.yaml"
    packaged, wide = BiMABConfig.load(), BiMABConfig.load(overlay)
    a, b = packaged.to_dict(), wide.to_dict()
    assert {k for k in a if a[k] != b[k]} == {"eta"} and wide.eta == 2 * packaged.eta
    for c in (packaged, wide):
        s = make_scheduler("bimab", seed=1, total_episodes=2000, config=c)
        for _ in range(2000):
            i, j = s.sample()
            s.update(i, j, 100.0 if (i, j) == (3, 0) else 0.0)
        p_c, p_a = s.probabilities()
        floor_c, floor_a = c.eta / p_c.size, c.eta / p_a.shape[1]
        assert floor_c - 1e-12 <= p_c.min() < floor_c + 0.02, (c.eta, p_c)
        assert p_a.min() >= floor_a - 1e-12, (c.eta, p_a)
