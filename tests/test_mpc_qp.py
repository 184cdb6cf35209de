"""The SQP's QP (``_kernels.qp_null_space``) on the QPs of closed-loop problems: its answer meets
the KKT conditions of the convexified QP it reports (Hc = H + rho * sum_A G_i'G_i + tau * I):
feasible, the working set active, stationary with non-negative multipliers, and Hc positive
definite on the working set's null space, so the answer is the QP's minimum there. Both the
Gauss-Newton Hessian (positive definite: rho = tau = 0 and the minimum is global) and the exact
one (often indefinite) are checked, from cold starts and from the SQP's iterates. The other
outcomes keep their contracts: a numerically dependent blocking row (code 1) leaves a feasible
step; an exact Hessian whose negative curvature no shift up to max |H_ii| removes (code 2, on
cold guesses far from the optimum) is left to the SQP's Gauss-Newton fallback."""
import numpy as np
import pytest

from bimacppo_mpc import MPCConfig
from bimacppo_mpc import _kernels as K
from bimacppo_mpc.bench import BenchConfig, generate_problems
from bimacppo_mpc.controller import pack_params

CFG = MPCConfig.load()
P = pack_params(CFG)
N = CFG.horizon
n = 2 * N


@pytest.fixture(scope="module")
def episodes():
    return generate_problems(CFG, BenchConfig.load(), episodes=6)


def _qps(episodes, exact):
    """(H, g, G, b, W0) at each problem's projected cold guess and after one SQP step from it."""
    for ep in episodes:
        for t in range(0, len(ep.X0), 6):
            x0, ref, up = ep.X0[t], ep.Xref[t], ep.Uprev[t]
            xr, vlo, vhi = np.empty(4), np.empty(N), np.empty(N)
            zlo, zhi = np.empty(n), np.empty(n)
            assert K.prepare(x0, ref, up, P, xr, vlo, vhi, zlo, zhi) == K.ST_OK
            z, X = np.empty(n), np.empty((N + 1, 4))
            K.initial_guess(x0, xr, up, np.zeros((N, 2)), False, np.ones(5, dtype=np.bool_), P, vlo, vhi, zlo,
                            zhi, z, X)
            wk = K.sqp_workspace(N, P)
            S, lam, g, H, qk, G, h, b = wk[:8]
            K.build_constraints(x0[2], vlo, vhi, zlo, zhi, P, G, h)
            for _ in range(2):
                K.derivatives(x0, z, xr, up, P, exact, X, wk[14], S, lam, g, H)
                K.slacks(z, h, P[K.P_DT], b)
                yield H.copy(), g.copy(), G, b.copy(), np.flatnonzero(b <= 1e-12)[:n].astype(np.int64)
                # one SQP step (the QP's full step, projected) for the second QP
                z = z + _solve(H, g, G, b)[2]
                K.project(z, x0[2], vlo, vhi, zlo, zhi, P)


def _solve(H, g, G, b, W0=None):
    m = b.size
    W = np.zeros(n, dtype=np.int64)
    if W0 is None:
        W0 = np.flatnonzero(b <= 1e-12)[:n]
    W[:W0.size] = W0
    p, lamW, inW = np.empty(n), np.empty(n), np.zeros(m, dtype=np.bool_)
    qk = K.sqp_workspace(N, P)[4]
    dmax = np.abs(np.diag(H)).max()
    code, nW = K.qp_null_space(H, g, G, b, W, W0.size, 500, p, lamW, inW, dmax, P[K.P_DT], qk)
    return W[:nW].copy(), code, p, lamW[:nW].copy(), qk[16].copy(), qk[13][0][:n].copy()


@pytest.mark.parametrize("exact", [False, True])
def test_the_qp_answer_meets_the_kkt_conditions(episodes, exact):
    checked = convexified = total = 0
    for H, g, G, b, W0 in _qps(episodes, exact):
        W, code, p, lamW, cv, gq = _solve(H, g, G, b, W0)
        total += 1
        scale = 1.0 + np.abs(b).max()
        if code == 1:
            assert (G @ p - b).max() <= 1e-9 * scale
            continue
        if code == 2:
            assert exact, "the Gauss-Newton Hessian is positive definite: no shift is needed"
            continue
        assert code == 0
        rho, tau = cv[0], cv[1]
        if not exact:
            assert rho == 0.0 and tau == 0.0
        convexified += rho > 0.0 or tau > 0.0
        A = np.flatnonzero(b <= 1e-12)
        Hc = H + rho * G[A].T @ G[A] + tau * np.eye(n)
        assert (G @ p - b).max() <= 1e-9 * scale
        assert np.abs(G[W] @ p - b[W]).max(initial=0.0) <= 1e-9 * scale
        assert np.allclose(gq, g + Hc @ p, atol=1e-8 * (1.0 + np.abs(g).max()))
        resid = Hc @ p + g + G[W].T @ lamW
        assert np.abs(resid).max() <= 1e-7 * (1.0 + np.abs(g).max())
        assert lamW.min(initial=0.0) >= -1e-9 * (1.0 + np.abs(g).max())
        # Hc is positive definite on the null space of the working set
        _, sv, Vt = np.linalg.svd(G[W]) if W.size else (None, np.zeros(0), np.eye(n))
        Z = Vt[np.sum(sv > 1e-10):].T
        if Z.shape[1]:
            assert np.linalg.eigvalsh(Z.T @ Hc @ Z).min() > 0.0
        if not exact:
            assert np.linalg.eigvalsh(Hc).min() > 0.0          # convex: the minimum is global
        checked += 1
    assert checked >= (0.9 if not exact else 0.6) * total
    if exact:
        assert convexified > 0, "the exact Hessian's QPs should include indefinite ones"
