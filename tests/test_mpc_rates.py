"""Steering-rate and jerk bounds: they hold in every plan and between ticks, both solvers solve
the same bounded problem, the speed tube wins over the jerk bound, null restores the paper's
problem, and the config refuses bad values."""
import numpy as np
import pytest

from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_mpc import _kernels as K
from bimacppo_mpc.controller import pack_params

CFG = MPCConfig.load().replace(fast={"tol": 1e-10})
PAPER = CFG.replace(steer_rate_max=None, jerk_max=None)
TOL = 1e-9   # rounding only


def _rate_step(cfg=CFG):
    return cfg.steer_rate_max * cfg.dt


def _jerk_step(cfg=CFG):
    return cfg.jerk_max * cfg.dt


def _steering_moves(U, u_prev, cfg=CFG):
    d = np.r_[np.clip(u_prev[1], cfg.delta_min, cfg.delta_max), U[:, 1]]
    return np.abs(np.diff(d))


def _step(x, u, P):
    X = np.empty((2, 4))
    K.rollout(np.asarray(x, float), np.asarray(u, float).copy(), P, X)
    return X[1]


def test_default_config_bounds_both_rates():
    cfg = MPCConfig.load()
    assert cfg.steer_rate_max is not None and cfg.steer_rate_max > 0
    assert cfg.jerk_max is not None and cfg.jerk_max > 0
    # lock to lock takes more than one tick, and an emergency brake reaches a_min within a second
    assert cfg.steer_rate_max * cfg.dt < cfg.delta_max - cfg.delta_min
    assert -cfg.a_min / cfg.jerk_max <= 1.0


@pytest.mark.parametrize("solver", ["fast", "ipopt"])
def test_a_lock_to_lock_demand_is_met_at_the_steering_rate(solver):
    """Steering held at the left lock, the reference far to the right: without the bound the
    first move jumps across; with it every move of the plan is at most steer_rate_max * dt."""
    x0 = np.array([0.0, 0.0, 4.0, 0.0])
    ref = np.array([6.0, -6.0, 2.0, -1.2])
    up = np.array([0.0, CFG.delta_max])
    free = make_controller(PAPER, solver).solve(x0, ref, up)
    bounded = make_controller(CFG, solver).solve(x0, ref, up)
    assert free.ok and bounded.ok
    assert _steering_moves(free.U, up).max() > 2 * _rate_step()      # the bound is not idle here
    moves = _steering_moves(bounded.U, up)
    assert moves.max() <= _rate_step() + TOL
    assert bounded.u[1] == pytest.approx(CFG.delta_max - _rate_step(), abs=TOL)   # turns as fast as allowed


@pytest.mark.parametrize("seed", range(4))
def test_fast_and_ipopt_reach_the_same_bounded_optimum(seed):
    rng = np.random.default_rng(100 + seed)
    fast, ipopt = make_controller(CFG, "fast"), make_controller(CFG, "ipopt")
    psi = rng.uniform(-np.pi, np.pi)
    x0 = np.array([0.0, 0.0, rng.uniform(1, 5), psi])
    d, lat = rng.uniform(10, 15), rng.uniform(-4, 4)
    ref = np.array([d * np.cos(psi) - lat * np.sin(psi), d * np.sin(psi) + lat * np.cos(psi),
                    rng.choice([0.0, 2.0, 4.0]), psi + rng.uniform(-0.8, 0.8)])
    up = np.array([rng.uniform(-5, 3), rng.uniform(-0.6, 0.6)])
    a, b = fast.solve(x0, ref, up), ipopt.solve(x0, ref, up)
    assert a.ok and b.ok, (a.status, b.status)
    assert a.cost == pytest.approx(b.cost, rel=1e-6)
    assert np.allclose(a.U, b.U, atol=1e-3)
    for res in (a, b):
        assert _steering_moves(res.U, up).max() <= _rate_step() + TOL
        ap = np.clip(up[0], CFG.a_min, CFG.a_max)
        assert abs(res.u[0] - ap) <= _jerk_step() + TOL


def test_closed_loop_commands_never_jump_between_ticks():
    """A reference that switches sides every few ticks (the planner changing its mind) gives
    commands whose steering and acceleration move by at most one tick's worth of rate."""
    P = pack_params(CFG)
    ctrl = make_controller(CFG, "fast")
    x, u = np.array([0.0, 0.0, 5.0, 0.0]), np.zeros(2)
    moves = []
    for t in range(60):
        side = 1.0 if (t // 5) % 2 == 0 else -1.0
        ref = np.array([x[0] + 6.0, side * 5.0, 8.0 if t % 7 else 0.0, side * 0.8])
        res = ctrl.solve(x, ref, u)
        assert res.ok, res.status
        moves.append(np.abs(res.u - u))
        x, u = _step(x, res.u, P), res.u
        assert x[2] >= CFG.v_min - TOL
    moves = np.array(moves)
    assert moves[:, 1].max() <= _rate_step() + TOL
    assert moves[:, 0].max() <= _jerk_step() + TOL
    assert moves[:, 1].max() > 0.5 * _rate_step()          # the reference did ask for steering


def test_the_speed_bound_wins_over_the_jerk_bound():
    ctrl = make_controller(CFG, "fast")
    # the end of a hard stop: braking at a_min 0.3 m/s above v_min must ease to -3 m/s^2 at once,
    # further than jerk_max * dt allows; the first move goes exactly to the speed bound
    res = ctrl.solve([0.0, 0.0, 0.3, 0.0], [0.0, 0.0, 0.0, 0.0], [CFG.a_min, 0.0])
    assert res.ok
    assert res.u[0] == pytest.approx((CFG.v_min - 0.3) / CFG.dt, abs=TOL)
    assert res.u[0] - CFG.a_min > _jerk_step()
    assert np.all(res.X[1:, 2] >= CFG.v_min - TOL)
    # above v_max, cruising: the relaxed tube demands full braking at once
    ctrl.reset()
    v0 = CFG.v_max + 1.0
    res = ctrl.solve([0.0, 0.0, v0, 0.0], [30.0, 0.0, 8.0, 0.0], [0.0, 0.0])
    assert res.ok and res.u[0] == pytest.approx(CFG.a_min, abs=TOL)


def test_input_boxes_tighten_only_the_first_move():
    P = pack_params(CFG)
    N = CFG.horizon
    vlo, vhi = np.empty(N), np.empty(N)
    zlo, zhi = np.empty(2 * N), np.empty(2 * N)
    x0 = np.array([0.0, 0.0, 5.0, 0.0])
    up = np.array([2.9, -0.7])            # steering outside the box: clipped first
    assert K.speed_tube(x0[2], N, P, vlo, vhi)
    K.input_boxes(x0, up, vlo, vhi, P, zlo, zhi)
    assert zlo[0] == pytest.approx(2.9 - _jerk_step()) and zhi[0] == CFG.a_max
    assert zlo[1] == CFG.delta_min and zhi[1] == pytest.approx(CFG.delta_min + _rate_step())
    assert np.all(zlo[2::2] == CFG.a_min) and np.all(zhi[2::2] == CFG.a_max)
    assert np.all(zlo[3::2] == CFG.delta_min) and np.all(zhi[3::2] == CFG.delta_max)
    K.input_boxes(x0, up, vlo, vhi, pack_params(PAPER), zlo, zhi)
    assert zlo[0] == CFG.a_min and zhi[1] == CFG.delta_max


def test_second_start_ramps_to_the_steering_bound_as_fast_as_allowed():
    P = pack_params(CFG)
    N = CFG.horizon
    x0 = np.array([0.0, 0.0, 4.0, 0.0])
    xref = np.array([8.0, 8.0, 2.0, 1.5])            # to the left: the left bound is cheaper
    up = np.array([0.0, -0.2])
    vlo, vhi = np.empty(N), np.empty(N)
    zlo, zhi = np.empty(2 * N), np.empty(2 * N)
    assert K.speed_tube(x0[2], N, P, vlo, vhi)
    K.input_boxes(x0, up, vlo, vhi, P, zlo, zhi)
    z, X = np.empty(2 * N), np.empty((N + 1, 4))
    K.steer_bound_start(x0, xref, up, np.zeros(2 * N), P, vlo, vhi, zlo, zhi, z, X)
    ramp = np.minimum(-0.2 + _rate_step() * np.arange(1, N + 1), CFG.delta_max)
    assert np.allclose(z[1::2], ramp, atol=TOL)


def test_null_disables_the_bounds_and_gives_the_papers_problem():
    x0 = np.array([0.0, 0.0, 4.0, 0.0])
    ref = np.array([6.0, -6.0, 2.0, -1.2])
    up = np.array([0.0, CFG.delta_max])
    a = make_controller(PAPER, "fast").solve(x0, ref, up)
    b = make_controller(PAPER, "ipopt").solve(x0, ref, up)
    assert a.ok and b.ok and a.cost == pytest.approx(b.cost, rel=1e-6)
    assert abs(a.u[1] - up[1]) > 2 * _rate_step()
    assert make_controller(PAPER, "fast").P[K.P_STEER_RATE] == 0.0


def test_the_fallback_brakes_at_once_and_holds_the_steering():
    cfg = CFG.replace(fast={"max_iter": 0})
    res = make_controller(cfg, "fast").solve([0.0, 0.0, 5.0, 0.0], [10.0, 0.0, 4.0, 0.0], [CFG.a_max, 0.3])
    assert not res.ok
    assert res.u[0] == max(CFG.a_min, CFG.brake_decel)       # a jump of 6 m/s^2: safety first
    assert res.u[1] == 0.3


@pytest.mark.parametrize("key", ["steer_rate_max", "jerk_max"])
@pytest.mark.parametrize("bad", [0, -1.0, float("inf"), "fast", True])
def test_bad_rate_bounds_are_refused_naming_the_key(key, bad):
    with pytest.raises(ValueError, match=key):
        CFG.replace(**{key: bad})


@pytest.mark.parametrize("key", ["steer_rate_max", "jerk_max"])
def test_rate_bounds_accept_null_and_integers(key):
    assert getattr(CFG.replace(**{key: None}), key) is None
    assert getattr(CFG.replace(**{key: 2}), key) == 2.0
