"""The convexification's shift search (``_kernels.convexify``): on an indefinite Hessian with no
active row it returns H0 + tau I with tau just above -lambda_min, and the factor it leaves in Lh
is exactly the Cholesky factor of that matrix, whichever of its trials computed it (the
bisection factors into a spare buffer and keeps the factor of its last success)."""
import numpy as np
import pytest

from bimacppo_mpc import _kernels as K

N_VAR = 40


def _indefinite(seed):
    rng = np.random.default_rng(seed)
    Q, _ = np.linalg.qr(rng.standard_normal((N_VAR, N_VAR)))
    eig = rng.uniform(0.5, 50.0, N_VAR)
    eig[: rng.integers(1, 4)] = -rng.uniform(1e-3, 5.0)      # one to three negative directions
    return (Q * eig) @ Q.T


@pytest.mark.parametrize("seed", range(40))
def test_the_shift_search_returns_the_factor_of_the_shifted_matrix(seed):
    H = _indefinite(seed)
    H = 0.5 * (H + H.T)
    orig = H.copy()
    n = N_VAR
    G = np.eye(n)                      # rows with slack: none is active, so only the shift acts
    b = np.ones(n)
    H0 = np.empty_like(H)
    Lh = np.full_like(H, np.nan)
    spare = np.full_like(H, np.nan)    # scratch: never read before it is written
    dmax = np.abs(np.diag(H)).max()
    assert not K.cholesky(H.copy(), np.empty_like(H), n, K._MIN_PIVOT * dmax)
    assert K.convexify(H, Lh, G, b, H0, dmax, spare)
    shift = H - orig
    tau = shift[0, 0]
    off = ~np.eye(n, dtype=bool)
    assert np.array_equal(shift[off], np.zeros(n * n - n)), "only the diagonal moves"
    assert np.allclose(np.diag(shift), tau, rtol=1e-9, atol=1e-12 * dmax), "by one shift"
    lam_min = np.linalg.eigvalsh(orig).min()
    assert -lam_min < tau < 1.2 * -lam_min + 1e-3 * dmax
    ref = np.empty_like(H)
    assert K.cholesky(H.copy(), ref, n, K._MIN_PIVOT * dmax)
    assert np.array_equal(Lh, ref), "the factor in Lh is the factor of the returned H, bit for bit"
    assert np.allclose(Lh @ Lh.T, H, atol=1e-9 * dmax)


def test_a_shift_beyond_the_largest_diagonal_is_left_to_the_caller():
    """A Hessian whose negative curvature exceeds max |H_ii| cannot be shifted within the search
    (the shifts stop at max |H_ii|): convexify reports failure, and sqp_ws falls back to the
    Gauss-Newton Hessian, which it forms only then."""
    H = np.array([[1.0, 10.0], [10.0, 1.0]])        # eigenvalues -9 and 11, max |H_ii| = 1
    n = 2
    G = np.eye(n)
    b = np.ones(n)
    dmax = 1.0
    assert not K.convexify(H, np.empty_like(H), G, b, np.empty_like(H), dmax, np.empty_like(H))
