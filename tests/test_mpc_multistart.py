"""Two starts keep the cheaper local minimum; the parallel batch equals the serial one; thread settings."""
import numba
import numpy as np
import pytest

from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_mpc import _kernels as K

CFG = MPCConfig.load()
ONE_START = CFG.replace(fast={"steer_bound_start": False})

# The car 2 m before and 0.3 m left of a reference point it passes at 6.3 m/s, heading 0.27 rad
# left of it: easing through and turning right as fast as the steering rate allows are both
# strict local minima, and the warm-startless first start lands in the costlier one (a
# closed-loop benchmark problem).
X0 = np.array([9.416, 0.314, 6.331, 0.272])
REF = np.array([11.5, 0.0, 8.0, 0.0])
UPREV = np.array([-1.912, 0.12])


def test_second_start_finds_the_cheaper_minimum_on_a_nonconvex_problem():
    two = make_controller(CFG, "fast").solve(X0, REF, UPREV)
    one = make_controller(ONE_START, "fast").solve(X0, REF, UPREV)
    ipopt = make_controller(CFG, "ipopt").solve(X0, REF, UPREV)
    assert two.ok and one.ok and ipopt.ok
    assert two.cost < 0.8 * one.cost
    assert two.cost <= 1.01 * ipopt.cost
    assert two.iterations > one.iterations          # both starts are counted


def test_two_starts_are_never_costlier_than_one():
    rng = np.random.default_rng(5)
    two = make_controller(CFG, "fast")
    one = make_controller(ONE_START, "fast")
    for _ in range(8):
        x0 = np.r_[rng.uniform(-3, 3, 2), rng.uniform(0, 8), rng.uniform(-0.5, 0.5)]
        ref = np.r_[rng.uniform(0, 12), rng.uniform(-3, 3), rng.choice([0.0, 4.0, 8.0]), rng.uniform(-0.5, 0.5)]
        up = np.r_[rng.uniform(-2, 2), rng.uniform(-0.6, 0.6)]
        two.reset()
        one.reset()
        a, b = two.solve(x0, ref, up), one.solve(x0, ref, up)
        assert a.ok and b.ok
        assert a.cost <= b.cost * (1 + 1e-12)


def test_the_returned_plan_is_the_rollout_of_its_inputs_and_costs_what_it_says():
    """The kernel re-rolls the plan out only where the second start overwrote the states; with
    one start, two starts where the second wins, and two starts where the first keeps it, the
    states are the Euler rollout of the returned inputs and the cost is theirs, bit for bit."""
    rng = np.random.default_rng(8)
    cases = [(X0, REF, UPREV, CFG), (X0, REF, UPREV, ONE_START)]
    for _ in range(12):
        x0 = np.r_[rng.uniform(-3, 3, 2), rng.uniform(0, 8), rng.uniform(-0.5, 0.5)]
        ref = np.r_[rng.uniform(0, 12), rng.uniform(-3, 3), rng.choice([0.0, 4.0, 8.0]), rng.uniform(-0.5, 0.5)]
        cases.append((x0, ref, np.r_[rng.uniform(-2, 2), rng.uniform(-0.6, 0.6)], CFG))
    starts = set()
    for x0, ref, up, cfg in cases:
        ctrl = make_controller(cfg, "fast")
        r = ctrl.solve(x0, ref, up)
        assert r.ok
        starts.add(r.starts)
        X = np.empty_like(r.X)
        K.rollout(x0, r.U.ravel().copy(), ctrl.P, X)
        assert np.array_equal(X, r.X)
        xr = ref.copy()
        xr[3] = x0[3] + K.wrap_angle(ref[3] - x0[3])
        assert r.cost == K.cost_of(X, r.U.ravel().copy(), xr, up, ctrl.P)
    assert starts == {1, 2}


def _batch(B, seed=1):
    rng = np.random.default_rng(seed)
    X0 = np.c_[rng.uniform(-2, 2, (B, 2)), rng.uniform(0, 8, B), rng.uniform(-0.3, 0.3, B)]
    Xr = np.c_[rng.uniform(0, 15, B), rng.uniform(-3, 3, B), rng.choice([0, 2, 4, 6, 8], B), np.zeros(B)]
    Up = np.c_[rng.uniform(-2, 2, B), rng.uniform(-0.6, 0.6, B)]
    X0[3, 0] = np.nan                     # a faulty slot must not disturb its neighbours
    return X0, Xr, Up


def test_parallel_batch_equals_serial_batch_bitwise_over_two_steps():
    X0, Xr, Up = _batch(12)
    serial = make_controller(CFG, "fast")
    serial.set_threads(1)
    par = make_controller(CFG, "fast")
    par.set_threads(2)
    for _ in range(2):                    # the second step runs from the per-slot warm starts
        a, b = serial.solve_batch(X0, Xr, Up), par.solve_batch(X0, Xr, Up)
        assert np.array_equal(a.U, b.U) and np.array_equal(a.X, b.X, equal_nan=True)
        assert np.array_equal(a.cost, b.cost, equal_nan=True) and np.array_equal(a.iterations, b.iterations)
        assert a.status == b.status and a.ok.tolist() == b.ok.tolist()
        assert not a.ok[3] and a.ok[[0, 1, 2]].all()
        X0 = X0 + np.c_[0.1 * X0[:, 2], np.zeros((len(X0), 3))]
        Up = a.u


@pytest.mark.parametrize("workers", [1, 2, 5, 40])
def test_the_parallel_kernel_solves_every_slot_once_whatever_the_number_of_workers(workers):
    """The workers take slots from a shared counter: with fewer, as many or more workers than
    threads and than slots, every slot is solved exactly once (its warm start advanced once, as
    the serial kernel's) and the results are the serial kernel's."""
    X0, Xr, Up = _batch(17, seed=4)
    ctrl = make_controller(CFG, "fast")
    N, B = CFG.horizon, len(X0)

    def run(kernel, *extra):
        out = [np.zeros((B, N, 2)), np.zeros(B, dtype=np.bool_), np.zeros((B, 4)), np.full((B, N, 2), np.nan),
               np.full((B, N + 1, 4), np.nan), np.full(B, np.nan), np.full(B, -9, dtype=np.int64),
               np.full(B, -9, dtype=np.int64), np.full(B, -9, dtype=np.int64)]
        for _ in range(2):                 # the second pass runs from the warm starts of the first
            kernel(X0, Xr, Up, out[0], out[1], out[2], ctrl.guesses, ctrl.P, CFG.fast.max_iter,
                   CFG.fast.qp_max_iter, *out[3:], *extra)
        return out

    serial, par = run(K.solve_batch_kernel), run(K.solve_batch_parallel, workers)
    for a, b in zip(serial, par):
        assert np.array_equal(a, b, equal_nan=True)
    assert (par[6] >= 0).all() and (par[8] >= 0).all()       # every status and start count written


def test_batches_use_the_thread_pool_only_when_large_and_restore_the_thread_count(monkeypatch):
    calls = []
    serial, parallel = K.solve_batch_kernel, K.solve_batch_parallel
    monkeypatch.setattr(K, "solve_batch_kernel", lambda *a: (calls.append("serial"), serial(*a)))
    monkeypatch.setattr(K, "solve_batch_parallel", lambda *a: (calls.append(numba.get_num_threads()), parallel(*a)))
    one = K.solve_one_kernel
    monkeypatch.setattr(K, "solve_one_kernel", lambda *a: (calls.append("serial"), one(*a)))
    ctrl = make_controller(CFG, "fast")
    before = numba.get_num_threads()
    X0, Xr, Up = _batch(CFG.fast.parallel_min_batch + 2)
    small = CFG.fast.parallel_min_batch - 1
    ctrl.solve_batch(X0[:small], Xr[:small], Up[:small])
    ctrl.solve(X0[0], Xr[0], Up[0])
    assert calls == ["serial", "serial"]
    calls.clear()
    ctrl.set_threads(2)
    ctrl.solve_batch(X0, Xr, Up)
    assert calls == [min(2, numba.config.NUMBA_NUM_THREADS)] or calls == ["serial"]
    assert numba.get_num_threads() == before
    ctrl.set_threads(1)
    calls.clear()
    ctrl.solve_batch(X0, Xr, Up)
    assert calls == ["serial"]


def test_thread_settings_are_validated():
    ctrl = make_controller(CFG, "fast")
    ctrl.set_threads(0)
    assert ctrl.threads == numba.config.NUMBA_NUM_THREADS
    ctrl.set_threads(10_000)
    assert ctrl.threads == numba.config.NUMBA_NUM_THREADS
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(ValueError, match="threads"):
            ctrl.set_threads(bad)
    with pytest.raises(ValueError, match="fast.threads"):
        CFG.replace(fast={"threads": -1})
    with pytest.raises(ValueError, match="fast.parallel_min_batch"):
        CFG.replace(fast={"parallel_min_batch": 0})
    with pytest.raises(ValueError, match="fast.steer_bound_start"):
        CFG.replace(fast={"steer_bound_start": "yes"})


def test_the_gate_runs_the_second_start_only_where_it_can_matter():
    gated = make_controller(CFG, "fast")
    assert CFG.fast.steer_bound_gate
    hard = gated.solve(X0, REF, UPREV)            # new reference, steering held on its bound
    assert hard.ok and hard.starts == 2
    easy = gated.solve([0.0, 0.0, 4.0, 0.0], [12.0, 0.5, 4.0, 0.0], [0.0, 0.0])
    assert easy.ok and easy.starts == 1          # gentle steering: one start
    always = make_controller(CFG.replace(fast={"steer_bound_gate": False}), "fast")
    assert always.solve([0.0, 0.0, 4.0, 0.0], [12.0, 0.5, 4.0, 0.0], [0.0, 0.0]).starts == 2
    assert make_controller(ONE_START, "fast").solve(X0, REF, UPREV).starts == 1
    assert make_controller(CFG, "fast").solve([np.nan, 0, 0, 0], REF, UPREV).starts == 0
    with pytest.raises(ValueError, match="fast.steer_bound_gate"):
        CFG.replace(fast={"steer_bound_gate": 1})


def test_the_gate_sees_a_new_reference_per_slot_and_after_reset():
    ctrl = make_controller(CFG, "fast")
    X0b, Xrb, Upb = np.tile(X0, (2, 1)), np.tile(REF, (2, 1)), np.tile(UPREV, (2, 1))
    first = ctrl.solve_batch(X0b, Xrb, Upb)
    assert first.starts.tolist() == [2, 2]
    ctrl.reset(slots=[1])                          # slot 1 restarts: its reference is new again
    again = ctrl.solve_batch(X0b, Xrb, Upb)
    assert again.starts[1] == 2
    assert np.array_equal(again.U[1], first.U[1]) and again.cost[1] == first.cost[1]


def test_the_side_rule_explores_only_the_other_side():
    z = np.zeros(2 * CFG.horizon)
    for last, bound, explores in ((0.3, CFG.delta_max, False), (0.3, CFG.delta_min, True),
                                  (-0.2, CFG.delta_min, False), (-0.2, CFG.delta_max, True),
                                  (0.0, CFG.delta_max, True), (0.0, CFG.delta_min, True)):
        z[-1] = last
        assert K.second_start_explores(z, bound) is explores, (last, bound)
    with pytest.raises(ValueError, match="fast.steer_bound_other_side"):
        CFG.replace(fast={"steer_bound_other_side": "no"})


def test_the_side_rule_skips_only_second_starts_and_keeps_the_others_bitwise():
    """Solved from scratch each time, a problem the rule leaves to one start gets the one-start
    plan, and one where the second start still runs gets the plan of the gate without the rule."""
    from bimacppo_mpc.bench import BenchConfig, generate_problems
    assert CFG.fast.steer_bound_other_side and CFG.fast.steer_bound_gate
    ctrl = {name: make_controller(c, "fast") for name, c in (
        ("rule", CFG), ("either", CFG.replace(fast={"steer_bound_other_side": False})), ("one", ONE_START))}
    skipped = kept = 0
    for ep in generate_problems(CFG, BenchConfig.load(), episodes=3):
        for x0, ref, up in zip(ep.X0, ep.Xref, ep.Uprev):
            for c in ctrl.values():
                c.reset()
            r, e, o = (ctrl[k].solve(x0, ref, up) for k in ("rule", "either", "one"))
            assert r.ok and e.ok
            if r.starts == 1:
                assert o.ok and np.array_equal(r.U, o.U)
                skipped += e.starts == 2
            else:
                assert e.starts == 2 and np.array_equal(r.U, e.U) and r.iterations == e.iterations
                kept += 1
            if o.ok:                                 # a failed first start always gets the second
                assert r.cost <= o.cost * (1 + 1e-12)
    assert skipped > 0 and kept > 0


def _random_problems(n, seed):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        yield (np.r_[rng.uniform(-3, 3, 2), rng.uniform(0, 8), rng.uniform(-0.5, 0.5)],
               np.r_[rng.uniform(0, 12), rng.uniform(-3, 3), rng.choice([0.0, 4.0, 8.0]), rng.uniform(-0.5, 0.5)],
               np.r_[rng.uniform(-2, 2), rng.uniform(-0.6, 0.6)])


def test_the_cut_keeps_a_winning_second_start():
    assert CFG.fast.second_start_cut is not None
    full = make_controller(CFG.replace(fast={"second_start_cut": None}), "fast").solve(X0, REF, UPREV)
    cut = make_controller(CFG, "fast").solve(X0, REF, UPREV)
    assert cut.ok and cut.starts == 2
    assert cut.cost == full.cost and np.array_equal(cut.U, full.U)


def test_the_cut_saves_iterations_and_never_returns_worse_than_one_start():
    always = {"steer_bound_gate": False}
    full = make_controller(CFG.replace(fast={**always, "second_start_cut": None}), "fast")
    cut = make_controller(CFG.replace(fast=always), "fast")
    one = make_controller(ONE_START, "fast")
    it_full = it_cut = 0
    for x0, ref, up in _random_problems(24, seed=11):
        for c in (full, cut, one):
            c.reset()
        a, b, o = full.solve(x0, ref, up), cut.solve(x0, ref, up), one.solve(x0, ref, up)
        assert a.ok and b.ok and o.ok
        assert b.cost <= o.cost * (1 + 1e-12)        # an abandoned second start keeps the first result
        assert b.cost >= a.cost                      # the cut can only lose a win, never find a cheaper one
        it_full += a.iterations
        it_cut += b.iterations
    assert it_cut < it_full


def test_sqp_abandons_a_start_that_cannot_beat_the_bound():
    from bimacppo_mpc.controller import pack_params
    P = pack_params(CFG)
    N = CFG.horizon
    xr, vlo, vhi = np.empty(4), np.empty(N), np.empty(N)
    zlo, zhi = np.empty(2 * N), np.empty(2 * N)
    assert K.prepare(X0, REF, UPREV, P, xr, vlo, vhi, zlo, zhi) == K.ST_OK

    def run(j_bar):
        z = np.zeros(2 * N)
        K.project(z, X0[2], vlo, vhi, zlo, zhi, P)
        wk = K.sqp_workspace(N, P)
        K.build_constraints(X0[2], vlo, vhi, zlo, zhi, P, wk[5], wk[6])
        return K.sqp_ws(X0, xr, UPREV, z, P, 60, 200, vlo, vhi, zlo, zhi, np.empty((N + 1, 4)), wk, j_bar)

    st, J, it = run(np.inf)
    assert st == K.ST_OK and it > 0
    st_low, J_low, it_low = run(0.5 * J)              # the optimum itself is above this bound
    assert st_low == K.ST_ABANDONED and it_low < it
    P[K.P_CUT] = 0.0                                  # second_start_cut: null, never abandon
    assert run(0.5 * J)[0] == K.ST_OK


def test_the_cut_is_validated():
    assert CFG.replace(fast={"second_start_cut": None}).fast.second_start_cut is None
    for bad in (0.5, -1.0, "2"):
        with pytest.raises(ValueError, match="fast.second_start_cut"):
            CFG.replace(fast={"second_start_cut": bad})


def test_the_uncut_overlay_is_the_solver_before_the_cut_and_the_side_rule():
    # the solver the recorded training runs used: only the two keys added since differ
    from bimacppo_mpc.config import CONFIG_DIR
    uncut = MPCConfig.load(CONFIG_DIR / "mpc_uncut.yaml")
    assert uncut.fast.second_start_cut is None and not uncut.fast.steer_bound_other_side
    now = {"second_start_cut": CFG.fast.second_start_cut, "steer_bound_other_side": True}
    assert uncut.replace(fast=now).to_dict() == CFG.to_dict()
