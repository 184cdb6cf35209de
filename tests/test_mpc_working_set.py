"""The QP's working set never outgrows its n slots: a full working set takes no further row,
and hold and go problems (stopping on the spot, or a turn with the steering and acceleration
on their bounds, where the working set fills up) run through solve_batch without an
out-of-bounds access. numba does not check bounds by default, so an overfull working set
would write past its arrays and corrupt the heap (a later ``free(): invalid next size``);
the subprocess test runs the kernels with NUMBA_BOUNDSCHECK=1 and a fresh cache so that
such a write raises instead."""
import os
import subprocess
import sys
import tempfile

import numpy as np

from bimacppo_mpc import _kernels as K

# Two rows about 1e-5 rad apart and a third in their span: with n = 2 the first two fill the
# working set, and the third's residual (zero in exact arithmetic) rounds above the pivot test.
NEAR_PARALLEL = np.array([[0.6672432157058636, 0.4607751075579932],
                          [0.48157118346373806, 0.3325086278934417],
                          [0.0012326808666994523, 0.0008306569615112908]])


def _fill(G, n, slots):
    """Offer every row of G to an empty working set whose arrays have `slots` >= n rows (Y holds
    one solved row per working-set row)."""
    Lh = np.eye(n)
    Y = np.zeros((slots, n))
    Ls = np.zeros((slots, slots))
    y = np.zeros(n)
    tmp = np.zeros(slots)
    sizes = []
    nW = 0
    for c in range(G.shape[0]):
        nW = K._ws_add(Lh, G, c, Y, Ls, nW, n, y, tmp)
        sizes.append(nW)
    return sizes, Y, Ls


def test_a_full_working_set_takes_no_further_row():
    # arrays one slot larger than n, so a wrong append shows as size 3 instead of corrupting memory
    sizes, Y, Ls = _fill(NEAR_PARALLEL, 2, 3)
    assert sizes == [1, 2, 2]
    assert np.all(Y[2] == 0.0) and np.all(Ls[2] == 0.0)


def test_independent_rows_still_fill_the_working_set():
    rng = np.random.default_rng(0)
    G = rng.standard_normal((5, 4))
    sizes, Y, Ls = _fill(G, 4, 4)
    assert sizes == [1, 2, 3, 4, 4]
    # Ls is the Cholesky factor of Y Y' (the working set's Schur complement)
    assert np.allclose(Ls @ Ls.T, Y @ Y.T)


# Cold problems (found by probing the kernel) whose SQP has a QP step blocked by a row while the
# working set is already full: x0, x_ref (a turn of ~1.5 rad), u_prev.
FULL_WORKING_SET = [
    ([12.61, -16.64, 8.79, 2.03], [33.55, -5.29, 6.0, 0.5], [0.0, 0.0]),
    ([-25.81, 11.75, 9.28, 2.49], [-16.43, 24.06, 0.0, 0.92], [0.0, 0.0]),
    ([1.51, -10.33, 0.05, -1.5], [12.63, -1.7, 8.0, 0.66], [-3.0, 0.0]),
]

SCRIPT = r"""
import math, sys
import numpy as np
from bimacppo_mpc import MPCConfig, make_controller
from bimacppo_mpc import _kernels as K

G = np.array(%r)
n = 2
Y = np.zeros((n, n)); Ls = np.zeros((n, n)); y = np.zeros(n); tmp = np.zeros(n)
nW = 0
for c in range(3):
    nW = K._ws_add(np.eye(n), G, c, Y, Ls, nW, n, y, tmp)
assert nW == n, nW

cfg = MPCConfig.load()
ctrl = make_controller(cfg, "fast")
ctrl.set_threads(1)

def check(res):
    errors = [s for s in res.status if s.startswith("solver_error")]
    assert not errors, errors[0]

full = %r
check(ctrl.solve_batch(*(np.array([f[j] for f in full]) for j in range(3))))

rng = np.random.default_rng(7)
B, T, solved = 16, 15, 0
for episode in range(%d):
    x = np.zeros((B, 4))
    x[:, :2] = rng.uniform(-30.0, 30.0, (B, 2))
    x[:, 2] = rng.choice([0.0, 0.0, 0.05, 0.3, 1.0, 3.0, 6.0, 9.0], B)
    x[:, 3] = rng.uniform(-math.pi, math.pi, B)
    # the route's heading: along the car, or turned away from it (a stop ordered in a turn)
    heading = x[:, 3] + rng.choice([0.0, 0.3, -0.8, math.pi / 2, -math.pi / 2], B)
    u = np.stack([rng.choice([cfg.a_min, cfg.a_max, 0.0, -3.0], B),
                  rng.choice([cfg.delta_min, cfg.delta_max, 0.0], B)], 1)
    ctrl.reset()
    for t in range(T):
        # hold (here, at 0 m/s) or go (a point 5-25 m away along the route, at a planner speed)
        ref = np.stack([x[:, 0], x[:, 1], np.zeros(B), heading], 1)
        go = rng.uniform(size=B) < 0.5
        d = rng.uniform(5.0, 25.0, go.sum())
        ref[go, 0] += d * np.cos(heading[go])
        ref[go, 1] += d * np.sin(heading[go])
        ref[go, 2] = rng.choice([2.0, 4.0, 6.0, 8.0], go.sum())
        res = ctrl.solve_batch(x, ref, u)
        check(res)
        X = np.empty((2, 4))
        for i in range(B):
            K.rollout(x[i], res.u[i].copy(), ctrl.P, X)
            x[i] = X[1]
        u = res.u.copy()
        solved += B
print("SOLVED", solved)
"""


def test_hold_and_go_problems_stay_in_bounds_under_numba_boundscheck():
    episodes = 8
    code = SCRIPT % (NEAR_PARALLEL.tolist(), FULL_WORKING_SET, episodes)
    with tempfile.TemporaryDirectory() as cache:
        env = dict(os.environ, NUMBA_BOUNDSCHECK="1", NUMBA_CACHE_DIR=cache)
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=900, env=env)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip().endswith(f"SOLVED {episodes * 16 * 15}")


def _constraint_rows():
    """The packaged controller's constraint rows (bounds, speed tube, steering rate) and a
    positive definite Hessian factor of its size."""
    from bimacppo_mpc import MPCConfig
    from bimacppo_mpc.controller import pack_params
    cfg = MPCConfig.load()
    P = pack_params(cfg)
    N = cfg.horizon
    n = 2 * N
    m = K.n_rows(N, P)
    G, h = np.empty((m, n)), np.empty(m)
    zlo, zhi = np.full(n, -1.0), np.full(n, 1.0)
    K.build_constraints(3.0, np.zeros(N), np.full(N, 10.0), zlo, zhi, P, G, h)
    rng = np.random.default_rng(3)
    A = rng.standard_normal((n, n))
    H = A @ A.T + 0.5 * np.eye(n)
    Lh = np.zeros((n, n))
    assert K.cholesky(H, Lh, n, 0.0)
    return G, Lh, n, rng


def test_the_one_pass_rebuild_is_the_row_by_row_appends():
    """qp_active_set rebuilds its working set with all row solves in one pass over Lh; the set,
    its basis Y and factor Ls must be those of appending the rows one by one (the QP's iterates
    depend on them), also when rows are dependent (a bound and its mirror, more rows than n)."""
    G, Lh, n, rng = _constraint_rows()
    m = G.shape[0]
    dropped = 0
    for trial in range(40):
        nc = int(rng.integers(1, n + 1))
        cand = rng.choice(m, nc, replace=False).astype(np.int64)
        mirror = (cand[0] + n) % (2 * n)     # -G_i of a bound row: dependent on it
        if trial % 4 == 0 and cand[0] < 2 * n and nc > 1 and mirror not in cand:
            cand[-1] = mirror
        Y1, Ls1 = np.zeros((n, n)), np.zeros((n, n))
        y, tmp = np.zeros(n), np.zeros(max(n, m))
        W1, nW1 = [], 0
        for c in cand:
            nn = K._ws_add(Lh, G, c, Y1, Ls1, nW1, n, y, tmp)
            if nn > nW1:
                W1.append(int(c))
                nW1 = nn
        Y2, Ls2, W2 = np.zeros((n, n)), np.zeros((n, n)), np.zeros(n, dtype=np.int64)
        inW = np.zeros(m, dtype=np.bool_)
        nW2 = K._ws_rebuild(Lh, G, cand.copy(), nc, Y2, Ls2, n, W2, inW, np.zeros(n), np.zeros(max(n, m)),
                            np.zeros((n, n)), np.zeros(n, dtype=np.int64))
        assert nW2 == nW1 and list(W2[:nW2]) == W1
        assert sorted(np.flatnonzero(inW)) == sorted(W1)
        assert np.array_equal(Y2[:nW2], Y1[:nW1]) and np.array_equal(Ls2[:nW2, :nW2], Ls1[:nW1, :nW1])
        dropped += nc - nW1
    assert dropped > 0


def test_deleting_a_row_keeps_the_factor_of_the_rest():
    """Dropping working-set row a leaves Ls the Cholesky factor of Y Y' without row and column
    a: lower triangular with a positive diagonal, zero outside the remaining rows."""
    rng = np.random.default_rng(5)
    n = 12
    for nW in (1, 2, 5, 9):
        for a in range(nW):
            Y = rng.standard_normal((nW, n))
            Ls = np.zeros((n, n))
            Ls[:nW, :nW] = np.linalg.cholesky(Y @ Y.T)
            K._ws_delete(Ls, nW, a)
            rest = np.delete(Y, a, axis=0)
            m = nW - 1
            assert np.allclose(Ls[:m, :m], np.linalg.cholesky(rest @ rest.T) if m else np.zeros((0, 0)))
            assert np.all(np.diag(Ls)[:m] > 0.0)
            assert np.all(np.triu(Ls, 1) == 0.0) and np.all(Ls[m:] == 0.0) and np.all(Ls[:, m:] == 0.0)
