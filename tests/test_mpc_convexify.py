"""The convexification of the QP (``_kernels.factor_reduced``), which acts on the reduced Hessian
Z'(H + rho * sum_A G_i'G_i + tau * I)Z only: rho stays 0 while that is positive definite, then
takes the first of dmax * 10^t that makes it so; only then is the smallest shift tau searched
(trials x8, then bisection), and the factor it leaves is exactly the Cholesky factor of the
matrix it settles on, whichever trial computed it."""
import numpy as np
import pytest

from bimacppo_mpc import _kernels as K

NF = 30


def _indefinite(seed, n=NF):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    eig = rng.uniform(0.5, 50.0, n)
    eig[: rng.integers(1, 4)] = -rng.uniform(1e-3, 5.0)      # one to three negative directions
    H = (Q * eig) @ Q.T
    return 0.5 * (H + H.T)


def _factor(Hb, R, ZtZ, dmax):
    n = Hb.shape[0]
    Hr, Lr, Lsp = np.full((n, n), np.nan), np.full((n, n), np.nan), np.full((n, n), np.nan)
    cv = np.zeros(6)
    ok = K.factor_reduced(Hr, np.tril(Hb), np.tril(R), np.tril(ZtZ), Lr, Lsp, n, dmax, cv)
    return ok, Lr, cv


@pytest.mark.parametrize("seed", range(30))
def test_the_shift_search_returns_the_factor_of_the_shifted_matrix(seed):
    H = _indefinite(seed)
    n = NF
    rng = np.random.default_rng(100 + seed)
    B = rng.standard_normal((n, n))
    ZtZ = B @ B.T / n + np.eye(n)             # a basis' Gram matrix: positive definite, not I
    dmax = np.abs(np.diag(H)).max()
    ok, Lr, cv = _factor(H, np.zeros((n, n)), ZtZ, dmax)
    assert ok
    rho, tau = cv[0], cv[1]
    assert rho == 0.0, "no active row outside the working set: nothing for rho to act on"
    # tau is just above the smallest shift that makes H + tau ZtZ positive definite
    Li = np.linalg.cholesky(ZtZ)
    crit = -np.linalg.eigvalsh(np.linalg.solve(Li, np.linalg.solve(Li, H).T)).min()
    assert crit < tau < 1.2 * crit + 1e-3 * dmax
    ref = np.empty((n, n))
    assert K.cholesky(H + tau * ZtZ, ref, n, K._MIN_PIVOT * dmax)
    assert np.array_equal(np.tril(Lr), np.tril(ref)), "the factor is that of the returned matrix, bit for bit"


def test_rho_rises_only_as_far_as_needed():
    """Negative curvature only along the directions of active rows outside the working set:
    the first rho of the ladder that removes it is taken, and no shift."""
    rng = np.random.default_rng(4)
    n = NF
    Q, _ = np.linalg.qr(rng.standard_normal((n, n)))
    eig = rng.uniform(1.0, 10.0, n)
    eig[0] = -25.0
    H = (Q * eig) @ Q.T
    H = 0.5 * (H + H.T)
    w = Q[:, 0]                                # the row's direction in the basis
    R = np.outer(w, w)
    dmax = np.abs(np.diag(H)).max()
    ok, Lr, cv = _factor(H, R, np.eye(n), dmax)
    assert ok and cv[1] == 0.0
    rho = cv[0]
    assert np.linalg.eigvalsh(H + rho * R).min() > 0.0
    ladder = [dmax * K._RHO_GROWTH ** t for t in range(K._RHO_TRIES)]
    assert rho in ladder
    smaller = [r for r in ladder if r < rho]
    assert all(np.linalg.eigvalsh(H + r * R).min() <= K._MIN_PIVOT * dmax for r in smaller)
    # positive definite already: nothing is added
    ok, _, cv = _factor(np.eye(n) * 3.0, R, np.eye(n), 3.0)
    assert ok and cv[0] == 0.0 and cv[1] == 0.0


def test_a_shift_beyond_the_largest_diagonal_is_left_to_the_caller():
    """A Hessian whose negative curvature exceeds max |H_ii| cannot be shifted within the search
    (the shifts stop at max |H_ii|): the factorisation reports failure, and sqp_ws falls back to
    the Gauss-Newton Hessian, which it forms only then."""
    H = np.array([[1.0, 10.0], [10.0, 1.0]])        # eigenvalues -9 and 11, max |H_ii| = 1
    ok, _, _ = _factor(H, np.zeros((2, 2)), np.eye(2), 1.0)
    assert not ok
