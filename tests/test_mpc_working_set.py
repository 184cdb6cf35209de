"""The QP's working set: its chain structure (which rows are independent, the null-space basis,
the multipliers) is the linear algebra of its rows; the Schur-complement part never outgrows
its n slots (a full working set takes no further row); and hold and go problems (stopping on
the spot, or a turn with the steering and acceleration on their bounds, where the working set
fills up) run through solve_batch without an out-of-bounds access. numba does not check bounds
by default, so an overfull working set would write past its arrays and corrupt the heap (a
later ``free(): invalid next size``); the subprocess test runs the kernels with
NUMBA_BOUNDSCHECK=1 and a fresh cache so that such a write raises instead."""
import os
import subprocess
import sys
import tempfile

import numpy as np
import pytest

from bimacppo_mpc import _kernels as K

# Two rows about 1e-5 rad apart and a third in their span: with n = 2 the first two fill the
# working set, and the third's residual (zero in exact arithmetic) rounds above the pivot test.
NEAR_PARALLEL = np.array([[0.6672432157058636, 0.4607751075579932],
                          [0.48157118346373806, 0.3325086278934417],
                          [0.0012326808666994523, 0.0008306569615112908]])


def _fill(G, n, slots):
    """Offer every row of G (solved against the identity factor) to an empty working set whose
    arrays have `slots` >= n rows (Y holds one solved row per working-set row)."""
    Y = np.zeros((slots, n))
    Ls = np.zeros((slots, slots))
    tmp = np.zeros(slots)
    sizes = []
    nW = 0
    for c in range(G.shape[0]):
        nW = K._ws_append(G[c].copy(), 0, Y, Ls, nW, n, tmp)
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
Y = np.zeros((n, n)); Ls = np.zeros((n, n)); tmp = np.zeros(n)
nW = 0
for c in range(3):
    nW = K._ws_append(G[c].copy(), 0, Y, Ls, nW, n, tmp)
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


def _constraints(rate=True):
    """The packaged controller's constraint rows (bounds, speed tube and, with ``rate``, the
    steering rate) in the order of build_constraints."""
    from bimacppo_mpc import MPCConfig
    from bimacppo_mpc.controller import pack_params
    cfg = MPCConfig.load()
    if not rate:
        cfg = cfg.replace(steer_rate_max=None)
    P = pack_params(cfg)
    N = cfg.horizon
    n = 2 * N
    m = K.n_rows(N, P)
    G, h = np.empty((m, n)), np.empty(m)
    zlo, zhi = np.full(n, -1.0), np.full(n, 1.0)
    K.build_constraints(3.0, np.zeros(N), np.full(N, 10.0), zlo, zhi, P, G, h)
    return G, N, P[K.P_DT]


def _working_set(G, N, dt, cand):
    """The rows of cand the QP keeps (in order, each if independent of those before) and the
    chain structure they leave."""
    link = np.full(2 * N, -1, dtype=np.int64)
    fix = np.full(2 * N, -1, dtype=np.int64)
    rows = np.array(cand, dtype=np.int64)
    nk = K.add_rows(rows, rows.size, N, dt, link, fix, True)
    return [int(c) for c in rows[:nk]], link, fix


def _basis(N, dt, link, fix):
    n = 2 * N
    lab = np.empty(n, dtype=np.int64)
    colptr = np.empty(n + 1, dtype=np.int64)
    zidx, zval = np.empty(n * N + 3 * N, dtype=np.int64), np.empty(n * N + 3 * N)
    iv = np.zeros((n, 3), dtype=np.int64)
    nf = K.chain_basis(N, dt, link, fix, lab, colptr, zidx, zval, iv, np.empty((2 * N, 4), dtype=np.int64))
    Z = np.zeros((n, nf))
    for c in range(nf):
        Z[zidx[colptr[c]:colptr[c + 1]], c] = zval[colptr[c]:colptr[c + 1]]
    return Z, lab, iv


@pytest.mark.parametrize("rate", [True, False])
def test_the_chain_structure_is_the_linear_algebra_of_the_rows(rate):
    """For random sets of constraint rows (bounds and their mirrors, speed rows, steering-rate
    rows): the rows kept are linearly independent and every row dropped lies in their span; the
    basis of the free chains spans exactly their null space; the multipliers solve
    G_W' lam = r for every r in the rows' range; the per-row flags and reduced rows say which
    rows move along the basis, and by how much."""
    G, N, dt = _constraints(rate)
    m, n = G.shape
    rng = np.random.default_rng(11)
    dropped = 0
    for trial in range(60):
        cand = rng.choice(m, int(rng.integers(1, n + 8)), replace=False).astype(np.int64)
        kept, link, fix = _working_set(G, N, dt, cand)
        GW = G[kept]
        assert np.linalg.matrix_rank(GW) == len(kept)
        assert np.linalg.matrix_rank(G[cand]) == len(kept), "a dropped row was independent"
        dropped += len(cand) - len(kept)
        Z, lab, iv = _basis(N, dt, link, fix)
        assert Z.shape[1] == n - len(kept)
        assert np.abs(GW @ Z).max(initial=0.0) < 1e-12
        assert np.linalg.matrix_rank(Z) == Z.shape[1]
        r = rng.standard_normal(len(kept)) @ GW
        lamr, rq = np.full(m, np.nan), np.empty(n)
        K.working_set_multipliers(r.copy(), N, dt, link, fix, lamr, rq, np.empty((2 * N, 4), dtype=np.int64))
        lam_ref = np.linalg.lstsq(GW.T, r, rcond=None)[0]
        assert np.allclose(lamr[kept], lam_ref, rtol=1e-9, atol=1e-9 * np.abs(lam_ref).max(initial=1.0))
        mv = np.zeros(m, dtype=np.bool_)
        K.move_flags(N, lab, m, mv)
        GZ = G @ Z
        assert np.array_equal(mv, np.abs(GZ).max(axis=1, initial=0.0) > 1e-12)
        w = np.empty(n)
        for c in rng.choice(m, 12, replace=False):
            first = K.reduced_row(c, N, dt, iv, w, Z.shape[1])
            assert np.allclose(w[:Z.shape[1]], GZ[c], atol=1e-12)
            nz = np.flatnonzero(np.abs(GZ[c]) > 1e-12)
            assert first == (nz[0] if nz.size else Z.shape[1])
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
