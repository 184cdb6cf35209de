"""Closed loop on the bicycle model: convergence to a fixed reference, bounds never violated,
heading wrapping, batched solving equal to one-by-one solving."""
import math

import numpy as np
import pytest

from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_mpc import _kernels as K
from bimacppo_mpc.controller import pack_params

CFG = MPCConfig.load()
P = pack_params(CFG)
TOL = 1e-9  # rounding only

STARTS = [
    [0.0, 0.0, 0.0, 0.0],
    [0.0, 2.0, 5.0, 0.3],
    [0.0, -2.0, 8.0, -0.4],
    [5.0, 1.0, 3.0, 0.8],
    [-5.0, -3.0, 2.0, -0.5],
    [0.0, 0.0, CFG.v_max, 0.0],
]


def step(x, u):
    X = np.empty((2, 4))
    K.rollout(np.asarray(x, float), np.asarray(u, float).copy(), P, X)
    return X[1]


def assert_within_bounds(U, v):
    assert np.all(U[..., 0] >= CFG.a_min - TOL) and np.all(U[..., 0] <= CFG.a_max + TOL)
    assert np.all(U[..., 1] >= CFG.delta_min - TOL) and np.all(U[..., 1] <= CFG.delta_max + TOL)
    assert np.all(v >= CFG.v_min - TOL) and np.all(v <= CFG.v_max + TOL)


@pytest.mark.parametrize("x0", STARTS)
def test_tracking_a_fixed_stop_reference_converges_and_respects_bounds(x0):
    ctrl = make_controller(CFG, "fast")
    ref = np.array([20.0, 0.0, 0.0, 0.0])
    x, u = np.array(x0, float), np.zeros(2)
    for _ in range(150):
        res = ctrl.solve(x, ref, u)
        assert res.ok, res.status
        assert_within_bounds(res.U, res.X[1:, 2])       # the whole plan, not only u_0
        assert np.allclose(res.u, res.U[0])
        x, u = step(x, res.u), res.u
        assert CFG.v_min - TOL <= x[2] <= CFG.v_max + TOL
    assert math.hypot(x[0] - ref[0], x[1] - ref[1]) < 0.1
    assert abs(x[2]) < 0.05
    assert abs(K.wrap_angle(x[3] - ref[3])) < 0.2


def test_moving_reference_is_followed_onto_its_line():
    ctrl = make_controller(CFG, "fast")
    x, u = np.array([0.0, 1.0, 2.0, 0.2]), np.zeros(2)
    v_ref = 6.0
    for _ in range(80):
        ref = np.array([x[0] + 8.0, 0.0, v_ref, 0.0])    # a point 8 m ahead on the x axis
        res = ctrl.solve(x, ref, u)
        assert res.ok
        x, u = step(x, res.u), res.u
    assert abs(x[1]) < 0.3 and abs(x[3]) < 0.1
    # chasing a point that stays ahead biases the speed up, never down, and never past v_max
    assert v_ref - 0.1 < x[2] <= CFG.v_max + TOL


def test_heading_reference_is_wrapped_no_two_pi_jump():
    ctrl = make_controller(CFG, "fast")
    x0 = np.array([0.0, 0.0, 4.0, math.pi - 0.05])
    ref = np.array([-10.0, 1.0, 4.0, math.pi - 0.05])
    a = ctrl.solve(x0, ref, np.zeros(2))
    ctrl.reset()
    b = ctrl.solve(x0, ref + np.array([0, 0, 0, 2 * math.pi]), np.zeros(2))
    ctrl.reset()
    c = ctrl.solve(x0, np.array([-10.0, 1.0, 4.0, -math.pi + 0.05]), np.zeros(2))
    assert a.ok and b.ok and c.ok
    assert np.allclose(a.U, b.U, atol=1e-8)
    # a reference heading just across the -pi/pi seam is a small error, not a 2*pi one
    assert abs(c.U[:, 1]).max() < 0.3


def test_speed_out_of_bounds_is_relaxed_to_the_reachable_tube():
    ctrl = make_controller(CFG, "fast")
    x0 = np.array([0.0, 0.0, CFG.v_max + 1.0, 0.0])
    res = ctrl.solve(x0, np.array([30.0, 0.0, 8.0, 0.0]), np.zeros(2))
    assert res.ok
    v = res.X[1:, 2]
    # it brakes as hard as allowed until back under v_max, then stays within bounds
    k_back = int(np.argmax(v <= CFG.v_max + TOL))
    assert np.all(np.diff(np.r_[x0[2], v[:k_back + 1]]) < 0)
    assert np.all(v[k_back:] <= CFG.v_max + TOL)


def test_solve_batch_matches_independent_solves_and_keeps_per_slot_warm_starts():
    rng = np.random.default_rng(3)
    B = 5
    X0 = np.c_[rng.uniform(-2, 2, (B, 2)), rng.uniform(0, 8, B), rng.uniform(-0.3, 0.3, B)]
    Xr = np.c_[rng.uniform(5, 15, B), rng.uniform(-2, 2, B), rng.choice([0, 2, 4, 6, 8], B), np.zeros(B)]
    Up = np.zeros((B, 2))
    batch = make_controller(CFG, "fast")
    b1 = batch.solve_batch(X0, Xr, Up)
    assert b1.u.shape == (B, 2) and b1.ok.shape == (B,) and len(b1.status) == B and b1.cost.shape == (B,)
    single = make_controller(CFG, "fast")
    for i in range(B):
        single.reset()
        r = single.solve(X0[i], Xr[i], Up[i])
        assert np.allclose(r.U, b1.U[i], atol=1e-9) and r.cost == pytest.approx(b1.cost[i], rel=1e-12)
    # second step: every slot warm-starts from its own previous plan
    X1 = np.array([step(X0[i], b1.u[i]) for i in range(B)])
    b2 = batch.solve_batch(X1, Xr, b1.u)
    for i in range(B):
        single.reset()
        single._warm1[0] = b1.U[i]
        single._has1[0] = True
        single._ref1[0] = Xr[i]
        r = single.solve(X1[i], Xr[i], b1.u[i])
        assert np.allclose(r.U, b2.U[i], atol=1e-9)
    # a different batch size starts fresh slots instead of mixing them up
    b3 = batch.solve_batch(X0[:2], Xr[:2], Up[:2])
    assert np.allclose(b3.U, b1.U[:2], atol=1e-9)


def test_kernel_wraps_angles_by_the_shared_rule():
    """The kernels compile bimacppo_common.conventions.wrap_angle itself: same value for every
    angle, bit for bit, including the branch points +-pi and huge angles."""
    from bimacppo_common.conventions import wrap_angle

    rng = np.random.default_rng(0)
    angles = np.concatenate([rng.uniform(-50.0, 50.0, 2000), [0.0, math.pi, -math.pi, 3 * math.pi, -3 * math.pi,
                                                               1e9, -1e9, 1e-300, -1e-300]])
    for a in angles:
        assert K.wrap_angle(float(a)) == wrap_angle(float(a))
