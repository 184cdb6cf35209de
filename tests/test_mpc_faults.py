"""Faults never raise and never give a non-finite command: NaN/inf inputs, forced solver
failures, a solver that raises, infeasible speed bounds; bad shapes are clear errors."""
import math

import numpy as np
import pytest

from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_mpc import _kernels as K

CFG = MPCConfig.load()
X0 = np.array([0.0, 0.0, 5.0, 0.1])
REF = np.array([10.0, 1.0, 4.0, 0.0])
UPREV = np.array([0.5, 0.2])


def expected_fallback(x0, u_prev, cfg=CFG):
    a = max(cfg.a_min, cfg.brake_decel)
    if np.isfinite(x0[2]):
        a = max(a, (cfg.v_min - x0[2]) / cfg.dt)      # never brake through v_min
    d = u_prev[1] if np.isfinite(u_prev[1]) else 0.0
    return np.array([a, np.clip(d, cfg.delta_min, cfg.delta_max)])


def check_fallback(res, x0, u_prev, word, cfg=CFG):
    assert res.ok is False
    assert word in res.status
    assert np.all(np.isfinite(res.u))
    assert np.allclose(res.u, expected_fallback(x0, u_prev, cfg))
    assert cfg.a_min <= res.u[0] <= cfg.a_max and cfg.delta_min <= res.u[1] <= cfg.delta_max
    assert np.all(np.isfinite(res.U))


@pytest.fixture(scope="module", params=["fast", "ipopt"])
def ctrl(request):
    return make_controller(CFG, request.param)


@pytest.mark.parametrize("where, idx, value, word", [
    ("x0", 0, math.nan, "state"),
    ("x0", 2, math.inf, "state"),
    ("x_ref", 1, math.inf, "reference"),
    ("x_ref", 3, -math.inf, "reference"),
    ("u_prev", 0, math.nan, "u_prev"),
    ("u_prev", 1, math.nan, "u_prev"),
])
def test_non_finite_inputs_give_the_fallback(ctrl, where, idx, value, word):
    args = {"x0": X0.copy(), "x_ref": REF.copy(), "u_prev": UPREV.copy()}
    args[where][idx] = value
    ctrl.reset()
    res = ctrl.solve(**args)
    check_fallback(res, args["x0"], args["u_prev"], word)
    assert math.isnan(res.cost)
    if where == "x0":
        assert np.all(np.isnan(res.X))
    else:
        assert np.all(np.isfinite(res.X))


def test_fallback_after_a_failure_drops_the_warm_start(ctrl):
    ctrl.reset()
    ok = ctrl.solve(X0, REF, UPREV)
    assert ok.ok
    bad = ctrl.solve(np.array([math.nan, 0, 5, 0]), REF, UPREV)
    assert not bad.ok
    again = ctrl.solve(X0, REF, UPREV)
    ctrl.reset()
    fresh = ctrl.solve(X0, REF, UPREV)
    assert again.ok and np.allclose(again.U, fresh.U, atol=1e-6)


@pytest.mark.parametrize("solver", ["fast", "ipopt"])
def test_iteration_limit_zero_is_a_reported_failure(solver):
    cfg = CFG.replace(fast={"max_iter": 0}, ipopt={"max_iter": 0})
    res = make_controller(cfg, solver).solve(X0, REF, UPREV)
    check_fallback(res, X0, UPREV, "solver_failed", cfg)


def test_fallback_does_not_brake_below_v_min():
    ctrl = make_controller(CFG.replace(fast={"max_iter": 0}), "fast")
    x0 = np.array([0.0, 0.0, 0.1, 0.0])
    res = ctrl.solve(x0, REF, UPREV)
    assert not res.ok
    assert x0[2] + CFG.dt * res.u[0] >= CFG.v_min - 1e-12
    assert res.u[0] <= 0.0


def test_a_raising_solver_is_caught(monkeypatch):
    ctrl = make_controller(CFG, "fast")

    def boom(*args, **kwargs):
        raise RuntimeError("simulated solver crash")

    monkeypatch.setattr(K, "solve_batch_kernel", boom)
    monkeypatch.setattr(K, "solve_one_kernel", boom)
    res = ctrl.solve(X0, REF, UPREV)
    check_fallback(res, X0, UPREV, "simulated solver crash")
    b = ctrl.solve_batch(np.stack([X0, X0]), np.stack([REF, REF]), np.stack([UPREV, UPREV]))
    assert not b.ok.any() and np.all(np.isfinite(b.u))


def test_a_raising_ipopt_is_caught():
    ctrl = make_controller(CFG, "ipopt")

    def boom(**kwargs):
        raise RuntimeError("simulated casadi error")

    ctrl._solver = boom
    res = ctrl.solve(X0, REF, UPREV)
    check_fallback(res, X0, UPREV, "simulated casadi error")


@pytest.mark.parametrize("solver", ["fast", "ipopt"])
def test_infeasible_speed_without_relaxation_is_reported(solver):
    cfg = CFG.replace(relax_infeasible_speed_bounds=False)
    x0 = np.array([0.0, 0.0, CFG.v_max + 2.0, 0.0])     # cannot get under v_max in one step
    res = make_controller(cfg, solver).solve(x0, REF, UPREV)
    check_fallback(res, x0, UPREV, "infeasible", cfg)


def test_batch_mixes_good_and_bad_slots():
    ctrl = make_controller(CFG, "fast")
    X = np.stack([X0, [math.nan, 0, 0, 0], X0])
    R = np.stack([REF, REF, [math.inf, 0, 0, 0]])
    U = np.stack([UPREV, UPREV, UPREV])
    b = ctrl.solve_batch(X, R, U)
    assert b.ok.tolist() == [True, False, False]
    assert "state" in b.status[1] and "reference" in b.status[2]
    assert np.all(np.isfinite(b.u))
    assert np.isfinite(b.cost[0]) and np.isnan(b.cost[1:]).all()


@pytest.mark.parametrize("args, name", [
    ((np.zeros(3), REF, UPREV), "x0"),
    ((X0, np.zeros((4, 1)), UPREV), "x_ref"),
    ((X0, REF, np.zeros(3)), "u_prev"),
    ((X0, ["a", "b", "c", "d"], UPREV), "x_ref"),
])
def test_bad_shapes_raise_clear_errors(args, name):
    ctrl = make_controller(CFG, "fast")
    with pytest.raises(ValueError, match=name):
        ctrl.solve(*args)


def test_batch_shape_errors_and_unknown_solver():
    ctrl = make_controller(CFG, "fast")
    with pytest.raises(ValueError, match="X0"):
        ctrl.solve_batch(np.zeros(4), np.zeros((1, 4)), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="Uprev"):
        ctrl.solve_batch(np.zeros((2, 4)), np.zeros((2, 4)), np.zeros((3, 2)))
    with pytest.raises(ValueError, match="solver"):
        make_controller(CFG, "acados")
