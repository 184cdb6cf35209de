"""numba kernels of the fast NMPC solver (see docs/mpc.md, "fast solver").

The problem is eq. (32)-(33) in single shooting: the decision vector is
z = [a_0, delta_0, a_1, delta_1, ...] (n = 2N) and the states are functions of z.
Because v_k = v_0 + dt * sum_{j<k} a_j, the speed bounds are *linear* in z, and so are
the optional rate bounds (steering rate over the horizon, jerk on the first move, as boxes
and difference rows), so every constraint is linear and each problem's feasible set is a
polytope. The kernel runs a line-search SQP on it:

* the gradient by an adjoint pass, the exact Hessian (costates lambda_k times the curvature
  of the Euler step added to the tracking weights) or its Gauss-Newton part by a backward
  cost-to-go recursion over the forward sensitivities S_k = dx_k/dz (``derivatives``);
* each QP is solved exactly by a dense primal active-set method (range space, incremental
  Cholesky of the working-set Schur complement), warm-started with the previous working set;
* every iterate is feasible (a convex combination of feasible points), so the merit
  function is the cost itself and bounds hold exactly up to rounding, which a final
  forward clamp removes;
* after a full step the SQP stops without a new Hessian when the last QP's factors show
  that the next QP would find no decrease (``converged_after_step``).

A problem can be solved from a second start and the cheaper result kept (see
``steer_bound_start`` and its gate ``second_start_pays``): the closed-loop problems have
several strict local minima, and a warm-started chain otherwise stays in whichever one it
entered first.

Everything is compiled with ``cache=True`` so a fresh process pays the compile once per
machine, not per run. The batch kernel has a serial and a ``prange`` variant around the
same per-slot routine.
"""
import math

import numpy as np
from bimacppo_common import conventions as _conventions
from numba import njit, prange

# status codes shared with controller.py (STATUS_TEXT there)
ST_OK = 0
ST_MAX_ITER = 1
ST_LINESEARCH = 2
ST_QP = 3
ST_INFEASIBLE = 4
ST_NONFINITE_STATE = 5
ST_NONFINITE_REF = 6
ST_NONFINITE_UPREV = 7
ST_NONFINITE_RESULT = 8
ST_ABANDONED = 9           # a second start stopped early: it could not become the cheaper one

# indices into the packed parameter vector P (built by controller.pack_params)
P_L, P_DT, P_AMIN, P_AMAX, P_DMIN, P_DMAX, P_VMIN, P_VMAX = 0, 1, 2, 3, 4, 5, 6, 7
P_QX, P_QU, P_QDU = 8, 12, 14
P_BRAKE, P_RELAX, P_TOL, P_EXACT, P_STEER_START, P_STEER_GATE = 16, 17, 18, 19, 20, 21
P_STEER_RATE, P_JERK = 22, 23     # rate bounds [rad/s], [m/s^3]; 0 = no bound
P_CUT = 24                        # fast.second_start_cut; 0 = never abandon
P_OTHER_SIDE = 25                 # fast.steer_bound_other_side (part of the gate); 0 = either side
P_SIZE = 26

# numerical constants of the linear algebra (not tuning knobs: scale-free guards)
_EPS_PIVOT = 1e-12       # relative pivot below which a working-set row is dependent
_EPS_DIR = 1e-13         # |G_i s| below this is "parallel to constraint i"
_ARMIJO = 1e-4           # sufficient-decrease constant of the backtracking line search
_BACKTRACK = 0.5
_MIN_STEP = 1e-10
_EPS_ACTIVE = 1e-12      # constraint slack below this is treated as zero (active)
_EPS_LAM = 1e-11         # a working-set multiplier below -_EPS_LAM * max(1, |g|_inf) is negative
_MIN_PIVOT = 1e-6        # Hessian pivots below this (relative to max |H_ii|) count as singular
_RHO_TRIES = 4           # active-constraint curvature rho = max|H_ii| * _RHO_GROWTH^t, t < _RHO_TRIES
_RHO_GROWTH = 10.0
_SHIFT0 = 1e-4           # first trial diagonal shift, relative to max |H_ii|
_SHIFT_GROWTH = 8.0      # trial shifts grow by this factor (IPOPT uses 8 too) ...
_SHIFT_BISECT = 4        # ... then this many geometric bisection steps tighten it
# the second start replaces the first only if cheaper by more than this (relative): closer
# costs are the same minimum reached to within the convergence tolerance, and keeping the
# first start's copy keeps the result a smooth function of the data (warm-start chains)
_SAME_MINIMUM = 1e-6
# the gate of the second start (fast.steer_bound_gate, docs/mpc.md "Two starts"): it runs when
# the first solution holds the steering on a bound over at least _GATE_SAT_NUM/_GATE_SAT_DEN of
# the horizon and the reference is new (changed, or no warm start), or when that share is at
# least _GATE_PASS_NUM/_GATE_SAT_DEN and the predicted path comes closest to the reference point
# by step _GATE_KMIN_NUM/_GATE_KMIN_DEN of the horizon (the car passes it: the case with
# several minima). Integer ratios keep the test exact for every N.
_GATE_SAT_NUM = 2
_GATE_PASS_NUM = 3
_GATE_SAT_DEN = 5
_GATE_KMIN_NUM = 3
_GATE_KMIN_DEN = 4
_STEER_ON_BOUND = 1e-9   # |delta - bound| below this counts as on the bound
# the SQP stops after a full step when the next QP's decrease, estimated from the last QP's
# factors, is below this share of the tolerance (converged_after_step): a margin of 100 for
# the Hessian's change over the step, so the estimate says yes only where the QP would
_EARLY_STOP_MARGIN = 1e-2


# the project's one wrap rule (bimacppo_common.conventions), compiled for the kernels
wrap_angle = njit(cache=True)(_conventions.wrap_angle)


@njit(cache=True)
def rollout(x0, z, P, X):
    """Explicit Euler eq. (2) of the bicycle model eq. (1)."""
    N = z.size // 2
    L = P[P_L]
    dt = P[P_DT]
    for i in range(4):
        X[0, i] = x0[i]
    for k in range(N):
        a = z[2 * k]
        d = z[2 * k + 1]
        v = X[k, 2]
        psi = X[k, 3]
        X[k + 1, 0] = X[k, 0] + dt * v * math.cos(psi + d)
        X[k + 1, 1] = X[k, 1] + dt * v * math.sin(psi + d)
        X[k + 1, 2] = v + dt * a
        X[k + 1, 3] = psi + dt * 2.0 * v / L * math.sin(d)


@njit(cache=True)
def cost_of(X, z, xref, uprev, P):
    """Eq. (32)-(33): sum_{k=0}^{N} |x_k - x_ref|^2_Qx + sum_k |u_k|^2_Qu + |u_k - u_{k-1}|^2_Qdu."""
    N = z.size // 2
    J = 0.0
    for k in range(N + 1):
        for i in range(4):
            e = X[k, i] - xref[i]
            J += P[P_QX + i] * e * e
    for k in range(N):
        for i in range(2):
            u = z[2 * k + i]
            up = uprev[i] if k == 0 else z[2 * k - 2 + i]
            du = u - up
            J += P[P_QU + i] * u * u + P[P_QDU + i] * du * du
    return J


@njit(cache=True)
def speed_tube(v0, N, P, vlo, vhi):
    """Speed bounds for v_1..v_N; returns False if infeasible and relaxation is off.

    With v_0 outside [v_min, v_max] the bound of step k is moved to the speed reachable
    at full braking/acceleration, the nearest non-empty set (docs/mpc.md)."""
    dt = P[P_DT]
    ok = True
    for k in range(1, N + 1):
        reach_lo = v0 + k * dt * P[P_AMIN]
        reach_hi = v0 + k * dt * P[P_AMAX]
        lo = P[P_VMIN]
        hi = P[P_VMAX]
        if reach_lo > hi or reach_hi < lo:
            ok = False
        if P[P_RELAX] > 0.5:
            hi = max(hi, reach_lo)
            lo = min(lo, reach_hi)
        vlo[k - 1] = lo
        vhi[k - 1] = hi
    return ok or P[P_RELAX] > 0.5


@njit(cache=True)
def input_boxes(x0, uprev, vlo, vhi, P, zlo, zhi):
    """Per-variable bounds zlo <= z <= zhi: the input boxes, tightened on the first move by the
    rate bounds around u_prev (clipped into the box first).

    Steering: delta_0 within steer_rate * dt of delta_prev, never empty (holding is allowed).
    Jerk: a_0 within jerk * dt of a_prev; where that interval misses the accelerations that keep
    v_1 in the speed tube, the nearer end is moved onto the tube's interval (the speed bound
    wins, docs/mpc.md "Rate bounds"), so the polytope is never empty."""
    N = vlo.size
    dt = P[P_DT]
    for k in range(N):
        zlo[2 * k] = P[P_AMIN]
        zhi[2 * k] = P[P_AMAX]
        zlo[2 * k + 1] = P[P_DMIN]
        zhi[2 * k + 1] = P[P_DMAX]
    rate = P[P_STEER_RATE] * dt
    if rate > 0.0:
        dp = min(max(uprev[1], P[P_DMIN]), P[P_DMAX])
        zlo[1] = max(P[P_DMIN], dp - rate)
        zhi[1] = min(P[P_DMAX], dp + rate)
    jump = P[P_JERK] * dt
    if jump > 0.0:
        ap = min(max(uprev[0], P[P_AMIN]), P[P_AMAX])
        lo = max(P[P_AMIN], ap - jump)
        hi = min(P[P_AMAX], ap + jump)
        # the accelerations keeping v_1 in the tube (the interval project() clamps a_0 into)
        tlo = max(P[P_AMIN], (vlo[0] - x0[2]) / dt)
        thi = min(P[P_AMAX], (vhi[0] - x0[2]) / dt)
        if hi < tlo:
            hi = tlo
        if lo > thi:
            lo = thi
        zlo[0] = lo
        zhi[0] = hi


@njit(cache=True)
def n_rows(N, P):
    """Rows of G z <= h: input boxes (2n), speed tube (2N), steering rate (2(N-1) if bounded)."""
    m = 6 * N
    if P[P_STEER_RATE] > 0.0:
        m += 2 * (N - 1)
    return m


@njit(cache=True)
def project(z, v0, vlo, vhi, zlo, zhi, P):
    """Make z feasible in place, forward in k: delta_k into its box and within the steering
    rate of delta_{k-1}, a_k into its box and the speed tube. Each interval is non-empty
    given the previous steps, so the result is feasible."""
    N = z.size // 2
    dt = P[P_DT]
    rate = P[P_STEER_RATE] * dt
    v = v0
    for k in range(N):
        lo = zlo[2 * k + 1]
        hi = zhi[2 * k + 1]
        if rate > 0.0 and k > 0:
            dprev = z[2 * k - 1]
            lo = max(lo, dprev - rate)
            hi = min(hi, dprev + rate)
        z[2 * k + 1] = min(max(z[2 * k + 1], lo), hi)
        lo = max(zlo[2 * k], (vlo[k] - v) / dt)
        hi = min(zhi[2 * k], (vhi[k] - v) / dt)
        a = min(max(z[2 * k], lo), hi)
        z[2 * k] = a
        v = v + dt * a


@njit(cache=True)
def build_constraints(v0, vlo, vhi, zlo, zhi, P, G, h):
    """All constraints as G z <= h (rows: a/delta upper, a/delta lower, v upper, v lower, then,
    with a steering rate bound, delta_k - delta_{k-1} <= rate*dt and its mirror, k = 1..N-1)."""
    N = vlo.size
    n = 2 * N
    dt = P[P_DT]
    G[:, :] = 0.0
    for j in range(n):
        G[j, j] = 1.0
        G[n + j, j] = -1.0
        h[j] = zhi[j]
        h[n + j] = -zlo[j]
    for k in range(N):
        for j in range(k + 1):
            G[2 * n + k, 2 * j] = dt
            G[2 * n + N + k, 2 * j] = -dt
        h[2 * n + k] = vhi[k] - v0
        h[2 * n + N + k] = v0 - vlo[k]
    if h.size > 6 * N:
        r0 = 6 * N
        rate = P[P_STEER_RATE] * dt
        for k in range(1, N):
            G[r0 + k - 1, 2 * k - 1] = -1.0
            G[r0 + k - 1, 2 * k + 1] = 1.0
            G[r0 + N - 1 + k - 1, 2 * k - 1] = 1.0
            G[r0 + N - 1 + k - 1, 2 * k + 1] = -1.0
            h[r0 + k - 1] = rate
            h[r0 + N - 1 + k - 1] = rate


@njit(cache=True)
def slacks(z, h, dt, b):
    """b = h - G z for the rows of build_constraints, skipping their zeros (unit rows, speed
    rows over the accelerations): the nonzero products in the dense product's order."""
    n = z.size
    N = n // 2
    for j in range(n):
        b[j] = h[j] - z[j]
        b[n + j] = h[n + j] + z[j]
    for k in range(N):
        hi = h[2 * n + k]
        lo = h[2 * n + N + k]
        for j in range(k + 1):
            hi -= dt * z[2 * j]
            lo -= -dt * z[2 * j]
        b[2 * n + k] = hi
        b[2 * n + N + k] = lo
    if h.size > 6 * N:
        r0 = 6 * N
        for k in range(1, N):
            b[r0 + k - 1] = h[r0 + k - 1] + z[2 * k - 1] - z[2 * k + 1]
            b[r0 + N - 1 + k - 1] = h[r0 + N - 1 + k - 1] - z[2 * k - 1] + z[2 * k + 1]
    return b


@njit(cache=True)
def gradient(x0, z, xref, uprev, P, X, lam, g):
    """The cost's gradient at z by one backward (adjoint) pass, X = rollout(x0, z): the same
    derivative as ``derivatives``' g in O(N) instead of through the O(N^2) sensitivities."""
    N = z.size // 2
    L = P[P_L]
    dt = P[P_DT]
    for i in range(4):
        lam[N, i] = 2.0 * P[P_QX + i] * (X[N, i] - xref[i])
    for k in range(N - 1, -1, -1):
        v = X[k, 2]
        psi = X[k, 3]
        d = z[2 * k + 1]
        c = math.cos(psi + d)
        s = math.sin(psi + d)
        l0 = lam[k + 1, 0]
        l1 = lam[k + 1, 1]
        l2 = lam[k + 1, 2]
        l3 = lam[k + 1, 3]
        g[2 * k] = dt * l2
        g[2 * k + 1] = -dt * v * s * l0 + dt * v * c * l1 + dt * 2.0 * v / L * math.cos(d) * l3
        if k > 0:
            lam[k, 0] = l0 + 2.0 * P[P_QX] * (X[k, 0] - xref[0])
            lam[k, 1] = l1 + 2.0 * P[P_QX + 1] * (X[k, 1] - xref[1])
            lam[k, 2] = (l2 + dt * c * l0 + dt * s * l1 + dt * 2.0 / L * math.sin(d) * l3
                         + 2.0 * P[P_QX + 2] * (X[k, 2] - xref[2]))
            lam[k, 3] = l3 - dt * v * s * l0 + dt * v * c * l1 + 2.0 * P[P_QX + 3] * (X[k, 3] - xref[3])
    for k in range(N):
        for i in range(2):
            j = 2 * k + i
            u = z[j]
            up = uprev[i] if k == 0 else z[j - 2]
            g[j] += 2.0 * P[P_QU + i] * u + 2.0 * P[P_QDU + i] * (u - up)
            if k + 1 < N:
                g[j] -= 2.0 * P[P_QDU + i] * (z[j + 2] - u)


@njit(cache=True)
def derivatives(x0, z, xref, uprev, P, exact, X, S, lam, g, H):
    """Cost, gradient and (exact or Gauss-Newton) Hessian of the single-shooting cost; X, S and
    lam keep the rollout, the forward sensitivities and the costates at z, which
    ``hessian(..., False, ...)`` reuses for the Gauss-Newton Hessian where it is needed.

    The Hessian is sum_k V_k' C_k V_k with V_k = d(x_k, u_k)/dz and C_k the Hessian of stage
    k's Lagrangian (tracking weights plus the costate-weighted curvature of the Euler step;
    the weights alone for Gauss-Newton). It is assembled by a backward recursion on the
    cost-to-go curvature P_k = C_k^xx + A_k' P_{k+1} A_k: u_l's own block is
    C_l^uu + B_l' P_{l+1} B_l, and u_j (j < l) meets u_l only through x_l, so their block is
    (dx_l/du_j)' (C_l^xu + A_l' P_{l+1} B_l). That is O(N^2) small products instead of the
    O(N^3) of forming the sum term by term."""
    N = z.size // 2
    L = P[P_L]
    dt = P[P_DT]
    rollout(x0, z, P, X)
    J = cost_of(X, z, xref, uprev, P)
    # forward sensitivities: S[k] = dx_k/dz; columns >= 2k are zero and never written, so S
    # must come zeroed (sqp_workspace's is)
    for k in range(N):
        v = X[k, 2]
        psi = X[k, 3]
        d = z[2 * k + 1]
        c = math.cos(psi + d)
        s = math.sin(psi + d)
        a02 = dt * c
        a03 = -dt * v * s
        a12 = dt * s
        a13 = dt * v * c
        a32 = dt * 2.0 / L * math.sin(d)
        for j in range(2 * k):
            s0 = S[k, 0, j]
            s1 = S[k, 1, j]
            s2 = S[k, 2, j]
            s3 = S[k, 3, j]
            S[k + 1, 0, j] = s0 + a02 * s2 + a03 * s3
            S[k + 1, 1, j] = s1 + a12 * s2 + a13 * s3
            S[k + 1, 2, j] = s2
            S[k + 1, 3, j] = s3 + a32 * s2
        S[k + 1, 0, 2 * k] = 0.0
        S[k + 1, 1, 2 * k] = 0.0
        S[k + 1, 2, 2 * k] = dt
        S[k + 1, 3, 2 * k] = 0.0
        S[k + 1, 0, 2 * k + 1] = -dt * v * s
        S[k + 1, 1, 2 * k + 1] = dt * v * c
        S[k + 1, 2, 2 * k + 1] = 0.0
        S[k + 1, 3, 2 * k + 1] = dt * 2.0 * v / L * math.cos(d)
    # gradient and costates lam[k] = d(cost of x_k..x_N)/dx_k
    gradient(x0, z, xref, uprev, P, X, lam, g)
    hessian(z, X, S, lam, P, exact, H)
    return J


@njit(cache=True)
def hessian(z, X, S, lam, P, curv, Hm):
    """The single-shooting cost's Hessian at z into Hm: exact (curv: the tracking weights plus
    the costate-weighted curvature of the Euler step) or its Gauss-Newton part (the weights
    alone, always positive definite), from the rollout X, sensitivities S and costates lam
    that ``derivatives`` left at z (see its docstring for the recursion)."""
    N = z.size // 2
    n = 2 * N
    L = P[P_L]
    dt = P[P_DT]
    Pn = np.empty((4, 4))
    A = np.empty((4, 4))
    B = np.empty((4, 2))
    PA = np.empty((4, 4))
    PB = np.empty((4, 2))
    Kx = np.empty((4, 2))
    Pn[:, :] = 0.0
    for i in range(4):
        Pn[i, i] = 2.0 * P[P_QX + i]
    for k in range(N - 1, -1, -1):
        v = X[k, 2]
        psi = X[k, 3]
        d = z[2 * k + 1]
        c = math.cos(psi + d)
        s = math.sin(psi + d)
        for r in range(4):
            for q in range(4):
                A[r, q] = 1.0 if r == q else 0.0
        A[0, 2] = dt * c
        A[0, 3] = -dt * v * s
        A[1, 2] = dt * s
        A[1, 3] = dt * v * c
        A[3, 2] = dt * 2.0 / L * math.sin(d)
        B[0, 0] = 0.0
        B[1, 0] = 0.0
        B[2, 0] = dt
        B[3, 0] = 0.0
        B[0, 1] = -dt * v * s
        B[1, 1] = dt * v * c
        B[2, 1] = 0.0
        B[3, 1] = dt * 2.0 * v / L * math.cos(d)
        # costate-weighted second derivatives of the Euler step in (v_k, psi_k, delta_k)
        m_vp = 0.0
        m_vd = 0.0
        m_pp = 0.0
        m_dd = 0.0
        if curv:
            lx = lam[k + 1, 0]
            ly = lam[k + 1, 1]
            lp = lam[k + 1, 3]
            m_vp = dt * (-lx * s + ly * c)
            m_pp = dt * (-lx * v * c - ly * v * s)
            m_vd = m_vp + lp * dt * 2.0 / L * math.cos(d)
            m_dd = m_pp - lp * dt * 2.0 * v / L * math.sin(d)
        # PA = P_{k+1} A, PB = P_{k+1} B
        for r in range(4):
            for q in range(4):
                t = 0.0
                for i in range(4):
                    t += Pn[r, i] * A[i, q]
                PA[r, q] = t
            for q in range(2):
                t = 0.0
                for i in range(4):
                    t += Pn[r, i] * B[i, q]
                PB[r, q] = t
        # u_k's own block: C^uu + B' P B
        for q1 in range(2):
            for q2 in range(q1 + 1):
                t = 0.0
                for i in range(4):
                    t += B[i, q1] * PB[i, q2]
                Hm[2 * k + q1, 2 * k + q2] = t
        Hm[2 * k + 1, 2 * k + 1] += m_dd
        # Kx <- C^xu + A' P B
        for r in range(4):
            for q in range(2):
                t = 0.0
                for i in range(4):
                    t += A[i, r] * PB[i, q]
                Kx[r, q] = t
        Kx[2, 1] += m_vd
        Kx[3, 1] += m_pp
        # the blocks of u_j, j < k: (dx_k/du_j)' Kx
        for q in range(2):
            row = 2 * k + q
            for j in range(2 * k):
                Hm[row, j] = (S[k, 0, j] * Kx[0, q] + S[k, 1, j] * Kx[1, q] + S[k, 2, j] * Kx[2, q]
                              + S[k, 3, j] * Kx[3, q])
        # P_k = C^xx + A' P A (not needed at k = 0: x_0 is fixed)
        if k > 0:
            for r in range(4):
                for q in range(r + 1):
                    t = 0.0
                    for i in range(4):
                        t += A[i, r] * PA[i, q]
                    Pn[r, q] = t
                    Pn[q, r] = t
            for i in range(4):
                Pn[i, i] += 2.0 * P[P_QX + i]
            Pn[2, 3] += m_vp
            Pn[3, 2] += m_vp
            Pn[3, 3] += m_pp
    # input terms
    for k in range(N):
        for i in range(2):
            j = 2 * k + i
            qd = P[P_QDU + i]
            Hm[j, j] += 2.0 * P[P_QU + i] + 2.0 * qd
            if k + 1 < N:
                Hm[j, j] += 2.0 * qd
                Hm[j + 2, j] -= 2.0 * qd
    for j in range(n):
        for l in range(j):
            Hm[l, j] = Hm[j, l]


@njit(cache=True)
def converged_after_step(x0, z, xref, uprev, P, X, J, h, Lh, G, W, nW, lamW, Y, Ls, ws, lam, tol):
    """True when the next SQP iteration at the accepted full step z (states X, cost J) would
    stop at once: the QP's predicted decrease there is <= tol * (1 + J) with the same working
    set, estimated without a new Hessian.

    At z the working-set QP's step is p = -Lh^-T (I - Y' (Y Y')^-1 Y) Lh^-1 r with r = grad +
    G_W' lamW (the KKT residual under the multipliers of the QP just solved) and decrease
    1/2 |(I - Y' (Y Y')^-1 Y) Lh^-1 r|^2, where Lh and Y (= G_W Lh^-T) are the factors of the
    previous iterate's Hessian: after a full Newton step the two Hessians differ by the order
    of the step, so the estimate must be under _EARLY_STOP_MARGIN times the tolerance. The
    working set must still be active at z, and the updated multipliers non-negative (the QP's
    own test), or the next QP would move its working set. When the test holds, the next
    iteration would return z unchanged: the result is the same, one derivative evaluation,
    convexification and QP earlier."""
    n = z.size
    g = ws[0]
    b = ws[1]
    q = ws[2]
    tmp = ws[3]
    y = ws[4]
    r = ws[5]
    dlam = ws[6]
    gradient(x0, z, xref, uprev, P, X, lam, g)
    slacks(z, h, P[P_DT], b)
    gnorm = 1.0
    for i in range(n):
        gnorm = max(gnorm, abs(g[i]))
    for a in range(nW):
        if b[W[a]] > _EPS_ACTIVE:
            return False
    # r = g + G_W' lamW
    for a in range(nW):
        row = G[W[a]]
        la = lamW[a]
        for i in range(n):
            g[i] += la * row[i]
    fwd_solve(Lh, g, q, n)
    _project_off(q, Y, Ls, nW, n, tmp, y, dlam, r)
    for a in range(nW):
        # the multipliers the next QP would find: lamW + its correction
        if lamW[a] + dlam[a] < -_EPS_LAM * gnorm:
            return False
    pred = 0.0
    for i in range(n):
        pred += r[i] * r[i]
    return 0.5 * pred <= _EARLY_STOP_MARGIN * tol * (1.0 + J)


@njit(cache=True)
def _project_off(q, Y, Ls, nW, n, tmp, y, lam, r):
    """lam = -(Y Y')^-1 Y q and r = q + Y' lam: q with its part in the span of the working set's
    solved rows Y[:nW] (one per row: Y[a] = Lh^-1 G_W[a]; Ls the factor of Y Y') removed, and the
    multipliers that remove it."""
    for a in range(nW):
        t = 0.0
        for i in range(n):
            t += Y[a, i] * q[i]
        tmp[a] = t
    if nW > 0:
        fwd_solve(Ls, tmp, y, nW)
        bwd_solve(Ls, y, lam, nW)
    for a in range(nW):
        lam[a] = -lam[a]
    # r[i] = q[i] + sum_a Y[a, i] lam[a], the terms added in order of a, row by row of Y
    for i in range(n):
        r[i] = q[i]
    for a in range(nW):
        la = lam[a]
        for i in range(n):
            r[i] += Y[a, i] * la


@njit(cache=True)
def cholesky(A, Lc, m, min_pivot):
    """Lower Cholesky of A[:m,:m] into Lc; False if a pivot is <= min_pivot (not safely PD)."""
    for j in range(m):
        s = A[j, j]
        for k in range(j):
            s -= Lc[j, k] * Lc[j, k]
        if s <= min_pivot or s <= _EPS_PIVOT * abs(A[j, j]):
            return False
        d = math.sqrt(s)
        Lc[j, j] = d
        for i in range(j + 1, m):
            t = A[i, j]
            for k in range(j):
                t -= Lc[i, k] * Lc[j, k]
            Lc[i, j] = t / d
        for i in range(j):
            Lc[i, j] = 0.0
    return True


@njit(cache=True)
def fwd_solve(Lc, b, x, m):
    fwd_solve_from(Lc, b, x, m, 0)


@njit(cache=True)
def fwd_solve_from(Lc, b, x, m, start):
    """fwd_solve for b with b[:start] = 0, whose solution is zero there too."""
    for i in range(start):
        x[i] = 0.0
    for i in range(start, m):
        t = b[i]
        for k in range(start, i):
            t -= Lc[i, k] * x[k]
        x[i] = t / Lc[i, i]


@njit(cache=True)
def bwd_solve(Lc, b, x, m):
    for i in range(m - 1, -1, -1):
        t = b[i]
        for k in range(i + 1, m):
            t -= Lc[k, i] * x[k]
        x[i] = t / Lc[i, i]


@njit(cache=True)
def _ws_add(Lh, G, idx, Y, Ls, nW, n, y, tmp):
    """Append constraint idx to the working set if independent; returns the new size."""
    if nW >= n:
        return nW
    row = G[idx]
    # y = Lh^{-1} row is zero before the row's first nonzero, so the solve and the products
    # start there (the skipped terms are exact zeros: the results are the dense ones)
    start = _first_nonzero(row, n)
    fwd_solve_from(Lh, row, y, n, start)
    return _ws_append(y, start, Y, Ls, nW, n, tmp)


@njit(cache=True)
def _first_nonzero(row, n):
    """Index of row[:n]'s first nonzero entry (n if none)."""
    start = 0
    while start < n and row[start] == 0.0:
        start += 1
    return start


@njit(cache=True)
def _ws_append(y, start, Y, Ls, nW, n, tmp):
    """Append the solved row y = Lh^{-1} G_i (zero before ``start``) to the working set if it
    is independent of the rows there (as row nW of Y); returns the new size.

    n rows already span R^n, so the row is dependent whatever the pivot test says: with a
    full, ill-conditioned working set the residual dd (zero in exact arithmetic) can round
    above the test's threshold, and appending would write past Y, Ls and W (n slots each)."""
    if nW >= n:
        return nW
    yy = 0.0
    for i in range(start, n):
        yy += y[i] * y[i]
    for r in range(nW):
        t = 0.0
        for i in range(start, n):
            t += Y[r, i] * y[i]
        tmp[r] = t
    # l = Ls^{-1} (Y y)
    for r in range(nW):
        t = tmp[r]
        for k in range(r):
            t -= Ls[r, k] * tmp[k]
        tmp[r] = t / Ls[r, r]
    dd = yy
    for r in range(nW):
        dd -= tmp[r] * tmp[r]
    if dd <= _EPS_PIVOT * max(yy, 1e-300) or yy == 0.0:
        return nW
    for i in range(n):
        Y[nW, i] = y[i]
    for r in range(nW):
        Ls[nW, r] = tmp[r]
        Ls[r, nW] = 0.0
    Ls[nW, nW] = math.sqrt(dd)
    return nW + 1


@njit(cache=True)
def _ws_rebuild(Lh, G, cand, nc, Y, Ls, n, W, inW, y, tmp, Yc, starts):
    """The working set of the rows cand[:nc], in that order, dependent ones dropped; returns
    its size.

    The same appends as one _ws_add per row, with every row's solve Lh^{-1} G_i done first
    in one pass over Lh (each element's subtractions in the same order as fwd_solve_from,
    so the rows solve to the same values; a row's terms before its first nonzero are exact
    zeros): one read of Lh instead of one per row, and the columns of Yc side by side."""
    if nc == 0:
        return 0
    first = n
    for j in range(nc):
        starts[j] = _first_nonzero(G[cand[j]], n)
        first = min(first, starts[j])
    for i in range(first):
        for j in range(nc):
            Yc[i, j] = 0.0
    for i in range(first, n):
        for j in range(nc):
            tmp[j] = G[cand[j], i]
        for k in range(first, i):
            lik = Lh[i, k]
            for j in range(nc):
                tmp[j] -= lik * Yc[k, j]
        d = Lh[i, i]
        for j in range(nc):
            Yc[i, j] = tmp[j] / d if i >= starts[j] else 0.0
    nW = 0
    for j in range(nc):
        for i in range(n):
            y[i] = Yc[i, j]
        nn = _ws_append(y, starts[j], Y, Ls, nW, n, tmp)
        if nn > nW:
            W[nW] = cand[j]
            inW[cand[j]] = True
            nW = nn
    return nW


@njit(cache=True)
def _ws_delete(Ls, nW, a):
    """Ls, the Cholesky factor of the working set's Schur complement Y Y' (nW rows), becomes the
    factor with row and column a removed, in O((nW - a)^2).

    Y Y' without row and column a is L' L'^T, where L' is Ls without row a: lower triangular
    except one entry right of the diagonal in each row from a on. Givens rotations of
    neighbouring columns (an orthogonal factor between L' and L'^T) remove those entries from
    the left, leaving a triangular factor with a positive diagonal and a zero last column.
    Refactoring Y Y' instead costs O(nW^2 n)."""
    for i in range(a, nW - 1):
        for k in range(i + 2):
            Ls[i, k] = Ls[i + 1, k]
    for k in range(a, nW - 1):
        x = Ls[k, k]
        y = Ls[k, k + 1]
        r = math.hypot(x, y)
        if r == 0.0:
            continue
        c = x / r
        s = y / r
        for i in range(k, nW - 1):
            lk = Ls[i, k]
            lk1 = Ls[i, k + 1]
            Ls[i, k] = c * lk + s * lk1
            Ls[i, k + 1] = c * lk1 - s * lk
        Ls[k, k + 1] = 0.0
    for i in range(nW):
        Ls[i, nW - 1] = 0.0
        Ls[nW - 1, i] = 0.0


@njit(cache=True)
def qp_active_set(H, Lh, g, G, b, W, nW, maxit, p, lamW, inW, Y, Ls, Sm, ws, starts):
    """min 1/2 p'Hp + g'p s.t. G p <= b, from the feasible p = 0 (b >= 0).

    W[:nW] is the initial working set (rows assumed active at p = 0; dependent ones are
    dropped). Returns (code, nW): code 0 optimal, 1 iteration limit (p feasible, not optimal).
    """
    n = g.size
    m = b.size
    qg = ws[0]
    q = ws[1]
    s = ws[2]
    y = ws[3]
    tmp = ws[4]
    r = ws[5]
    lam = ws[6]
    slack = ws[7]
    Gs = ws[8]
    w = ws[9]
    N = n // 2
    dt = G[2 * n, 0]
    for i in range(n):
        p[i] = 0.0
    for i in range(m):
        # rows satisfied with equality up to rounding count as active
        slack[i] = b[i] if b[i] > _EPS_ACTIVE else 0.0
        inW[i] = False
    # rebuild the initial working set from the rows still active, dropping dependent ones
    # (W never holds a row twice: rows enter it only while not in it)
    cand = W[:nW].copy()
    nc = 0
    for c in cand:
        if slack[c] <= 0.0:
            cand[nc] = c
            nc += 1
    nW = _ws_rebuild(Lh, G, cand, nc, Y, Ls, n, W, inW, y, tmp, Sm, starts)
    gnorm = 1.0
    for i in range(n):
        gnorm = max(gnorm, abs(g[i]))
    # q = Lh^{-1} (H p + g) = Lh' p + Lh^{-1} g (H = Lh Lh'), with w = Lh' p kept up to date from
    # the steps (Lh' s = -r below): O(n) per iteration instead of a product with H and a solve
    fwd_solve(Lh, g, qg, n)
    for i in range(n):
        w[i] = 0.0
    for it in range(maxit):
        for i in range(n):
            q[i] = w[i] + qg[i]
        # lam = -(Y Y')^{-1} Y q ; r = q + Y' lam ; s = -Lh^{-T} r
        _project_off(q, Y, Ls, nW, n, tmp, y, lam, r)
        bwd_solve(Lh, r, s, n)
        for i in range(n):
            s[i] = -s[i]
        snorm = 0.0
        for i in range(n):
            snorm = max(snorm, abs(s[i]))
        alpha = 1.0
        block = -1
        if snorm > 0.0:
            # G s by the rows' structure (unit rows, prefix sums of dt * s_a)
            for j in range(n):
                Gs[j] = s[j]
                Gs[n + j] = -s[j]
            acc = 0.0
            for k in range(N):
                acc += dt * s[2 * k]
                Gs[2 * n + k] = acc
                Gs[2 * n + N + k] = -acc
            if m > 6 * N:
                for k in range(1, N):
                    t = s[2 * k + 1] - s[2 * k - 1]
                    Gs[6 * N + k - 1] = t
                    Gs[7 * N - 1 + k - 1] = -t
            for c in range(m):
                if inW[c]:
                    Gs[c] = 0.0
                    continue
                t = Gs[c]
                if t > _EPS_DIR:
                    ratio = slack[c] / t
                    if ratio < alpha:
                        alpha = ratio
                        block = c
            for i in range(n):
                p[i] += alpha * s[i]
                w[i] -= alpha * r[i]
            for c in range(m):
                if not inW[c]:
                    slack[c] = max(slack[c] - alpha * Gs[c], 0.0)
        if block >= 0:
            slack[block] = 0.0
            nn = _ws_add(Lh, G, block, Y, Ls, nW, n, y, tmp)
            if nn == nW:
                # numerically dependent blocking row: stop with the feasible p reached so far
                return 1, nW
            W[nW] = block
            inW[block] = True
            nW = nn
            continue
        # full step: p is the working-set optimum, lam its multipliers
        worst = -1
        wval = -_EPS_LAM * gnorm
        for a in range(nW):
            if lam[a] < wval:
                wval = lam[a]
                worst = a
        if worst < 0:
            for a in range(nW):
                lamW[a] = lam[a]
            return 0, nW
        inW[W[worst]] = False
        for a in range(worst, nW - 1):
            W[a] = W[a + 1]
            for i in range(n):
                Y[a, i] = Y[a + 1, i]
        _ws_delete(Ls, nW, worst)
        nW -= 1
    return 1, nW


@njit(cache=True)
def _add_active_curvature(H, G, b, rho):
    n = H.shape[0]
    for c in range(G.shape[0]):
        if b[c] > _EPS_ACTIVE:
            continue
        for i in range(n):
            gi = G[c, i]
            if gi == 0.0:
                continue
            for j in range(n):
                H[i, j] += rho * gi * G[c, j]


@njit(cache=True)
def _shift(H, H0, tau):
    """H = H0 + tau I."""
    n = H.shape[0]
    for i in range(n):
        for j in range(n):
            H[i, j] = H0[i, j]
        H[i, i] += tau


@njit(cache=True)
def _shifted_cholesky(H, H0, Lh, tau, min_pivot):
    _shift(H, H0, tau)
    return cholesky(H, Lh, H.shape[0], min_pivot)


@njit(cache=True)
def convexify(H, Lh, G, b, H0, dmax, Lspare):
    """Make H positive definite with the least change, keeping its negative curvature useful.

    1. rho * G_i' G_i for the constraints active at the current iterate: this leaves the
       QP's KKT conditions unchanged as long as those rows stay active (G_i p = 0); the exact
       Hessian of this cost is often indefinite only along inputs sitting on their bounds.
    2. Otherwise the smallest diagonal shift tau that makes it positive definite (found by
       bisection on Cholesky success, as IPOPT's inertia correction does): with tau just
       above -lambda_min, the step follows the negative-curvature direction far enough to
       leave saddle points (the straight-braking saddle between a left and a right swerve),
       which a Gauss-Newton or heavily damped step would converge to.
    3. If even that fails numerically (no shift up to max |H_ii| factors), it returns False and
       the caller falls back to the Gauss-Newton Hessian (positive definite), formed only then.

    The bisection factors its trials into whichever of Lh and Lspare does not hold the factor of
    the current upper end, so the factor of the shift it ends with is at hand, not computed again:
    the same shift and the same factor as one more ``_shifted_cholesky`` at it. Lspare is scratch.
    """
    n = H.shape[0]
    min_pivot = _MIN_PIVOT * dmax
    H0[:, :] = H
    rho = dmax
    for _ in range(_RHO_TRIES):
        _add_active_curvature(H, G, b, rho)
        if cholesky(H, Lh, n, min_pivot):
            return True
        H[:, :] = H0
        rho *= _RHO_GROWTH
    _add_active_curvature(H, G, b, rho / _RHO_GROWTH)
    H0[:, :] = H
    hi = _SHIFT0 * dmax
    while not _shifted_cholesky(H, H0, Lh, hi, min_pivot):
        hi *= _SHIFT_GROWTH
        if hi > dmax:
            return False
    lo = hi / _SHIFT_GROWTH
    La = Lh           # holds the factor of H0 + hi I
    Lb = Lspare       # the trials'
    in_lh = True
    for _ in range(_SHIFT_BISECT):
        mid = math.sqrt(lo * hi)
        if _shifted_cholesky(H, H0, Lb, mid, min_pivot):
            hi = mid
            La, Lb = Lb, La
            in_lh = not in_lh
        else:
            lo = mid
    if not in_lh:
        Lh[:, :] = La
    _shift(H, H0, hi)
    return True


@njit(cache=True)
def sqp_workspace(N, P):
    """The arrays of one SQP (allocated once per problem and shared by its starts)."""
    n = 2 * N
    m = n_rows(N, P)
    return (np.zeros((N + 1, 4, n)), np.zeros((N + 1, 4)), np.empty(n), np.empty((n, n)),
            np.zeros((n, n)), np.empty((m, n)), np.empty(m), np.empty(m), np.empty(n), np.empty(n),
            np.empty(n, dtype=np.int64), np.zeros(m, dtype=np.bool_), np.empty(n), np.empty((n, n)),
            np.zeros((n, n)), np.empty((n, n)), np.empty((10, max(n, m))), np.empty((N + 1, 4)),
            np.empty((n, n)), np.empty(n, dtype=np.int64))


@njit(cache=True)
def sqp(x0, xref, uprev, z, P, max_iter, qp_max_iter, vlo, vhi, zlo, zhi, X):
    """Solve one problem from the feasible initial guess z (overwritten). Returns (status, cost, iters)."""
    wk = sqp_workspace(z.size // 2, P)
    build_constraints(x0[2], vlo, vhi, zlo, zhi, P, wk[5], wk[6])
    return sqp_ws(x0, xref, uprev, z, P, max_iter, qp_max_iter, vlo, vhi, zlo, zhi, X, wk, np.inf)


@njit(cache=True)
def sqp_ws(x0, xref, uprev, z, P, max_iter, qp_max_iter, vlo, vhi, zlo, zhi, X, wk, j_bar):
    """sqp() on the workspace wk of sqp_workspace, whose G, h already hold build_constraints.

    j_bar is the cost this run has to beat to be of use (the first start's, for the second
    start; np.inf otherwise). The run stops with ST_ABANDONED at the first iterate whose cost,
    less second_start_cut times the QP's predicted decrease, is still above j_bar: the local
    model says that even a step that many times better than predicted leaves it the dearer
    result (docs/mpc.md, "the cut")."""
    N = z.size // 2
    n = 2 * N
    (S, lam, g, H, Lh, G, h, b, p, zt, W, inW, lamW, Y, Ls, Sm, ws, Xt, H0, starts) = wk
    m = h.size
    exact = P[P_EXACT] > 0.5
    tol = P[P_TOL]
    cut = P[P_CUT]
    dt = P[P_DT]
    slacks(z, h, dt, b)
    nW = 0
    for c in range(m):
        if b[c] <= _EPS_ACTIVE and nW < n:
            W[nW] = c
            nW += 1
    J = 0.0
    for it in range(max_iter):
        J = derivatives(x0, z, xref, uprev, P, exact, X, S, lam, g, H)
        slacks(z, h, dt, b)
        dmax = 0.0
        for i in range(n):
            dmax = max(dmax, abs(H[i, i]))
        if not cholesky(H, Lh, n, _MIN_PIVOT * dmax):
            if not convexify(H, Lh, G, b, H0, dmax, Sm):
                # the last resort: the Gauss-Newton Hessian at z (X, S, lam are still z's)
                hessian(z, X, S, lam, P, False, H)
                if not cholesky(H, Lh, n, 0.0):
                    return ST_QP, J, it
        code, nW = qp_active_set(H, Lh, g, G, b, W, nW, qp_max_iter, p, lamW, inW, Y, Ls, Sm, ws, starts)
        gp = 0.0
        for i in range(n):
            gp += g[i] * p[i]
        php = 0.0
        for i in range(n):
            t = 0.0
            for k in range(n):
                t += H[i, k] * p[k]
            php += p[i] * t
        pred = -(gp + 0.5 * php)
        if code == 0 and pred <= tol * (1.0 + J):
            return ST_OK, J, it
        if cut > 0.0 and J - cut * pred > j_bar:
            return ST_ABANDONED, J, it
        if gp >= 0.0:
            return ST_QP, J, it
        alpha = 1.0
        accepted = False
        while alpha >= _MIN_STEP:
            for i in range(n):
                zt[i] = z[i] + alpha * p[i]
            project(zt, x0[2], vlo, vhi, zlo, zhi, P)
            rollout(x0, zt, P, Xt)
            Jt = cost_of(Xt, zt, xref, uprev, P)
            if Jt <= J + _ARMIJO * alpha * gp:
                accepted = True
                break
            alpha *= _BACKTRACK
        if not accepted:
            # no decrease possible within rounding: accept z as stationary if the
            # predicted decrease is at the level of cost rounding error
            if pred <= 1e3 * tol * (1.0 + J):
                return ST_OK, J, it
            return ST_LINESEARCH, J, it
        for i in range(n):
            z[i] = zt[i]
        if (code == 0 and alpha == 1.0 and it + 1 < max_iter
                and converged_after_step(x0, z, xref, uprev, P, Xt, Jt, h, Lh, G, W, nW, lamW, Y, Ls, ws,
                                         lam, tol)):
            for k in range(N + 1):
                for i in range(4):
                    X[k, i] = Xt[k, i]
            return ST_OK, Jt, it + 1
        # the working set is kept: qp_active_set drops the rows no longer active at the new z
    rollout(x0, z, P, X)
    return ST_MAX_ITER, cost_of(X, z, xref, uprev, P), max_iter


@njit(cache=True)
def fallback(x0, uprev, P, u):
    """Brake within bounds, hold (clipped) steering: the safe command of every fault. It keeps
    the steering rate bound (holding) but not the jerk bound: a fault brakes at once."""
    a = max(P[P_AMIN], P[P_BRAKE])
    v0 = x0[2]
    if math.isfinite(v0) and v0 >= P[P_VMIN]:
        # do not brake through v_min in one step (standing still is the goal of braking)
        a = min(max(a, (P[P_VMIN] - v0) / P[P_DT]), 0.0)
    d = uprev[1]
    if not math.isfinite(d):
        d = 0.0
    u[0] = a
    u[1] = min(max(d, P[P_DMIN]), P[P_DMAX])


@njit(cache=True)
def initial_guess(x0, xref, uprev, warm, has_warm, guesses, P, vlo, vhi, zlo, zhi, z, X):
    """Cheapest projected candidate among the enabled guesses (config.INITIAL_GUESSES order)."""
    N = z.size // 2
    n = 2 * N
    zc = np.empty(n)
    best = np.inf
    for gidx in range(guesses.size):
        if not guesses[gidx]:
            continue
        if gidx == 0:
            if not has_warm:
                continue
            for k in range(N):
                src = min(k + 1, N - 1)
                zc[2 * k] = warm[src, 0]
                zc[2 * k + 1] = warm[src, 1]
        elif gidx == 1:
            for k in range(N):
                zc[2 * k] = uprev[0]
                zc[2 * k + 1] = uprev[1]
        elif gidx == 2:
            zc[:] = 0.0
        elif gidx == 3:
            # full braking (the projection stops it at v_min)
            for k in range(N):
                zc[2 * k] = P[P_AMIN]
                zc[2 * k + 1] = 0.0
        else:
            # constant acceleration reaching the reference speed at the end of the horizon
            acc = (xref[2] - x0[2]) / (N * P[P_DT])
            for k in range(N):
                zc[2 * k] = acc
                zc[2 * k + 1] = 0.0
        project(zc, x0[2], vlo, vhi, zlo, zhi, P)
        rollout(x0, zc, P, X)
        Jc = cost_of(X, zc, xref, uprev, P)
        if Jc < best:
            best = Jc
            z[:] = zc
    if best == np.inf:
        z[:] = 0.0
        project(z, x0[2], vlo, vhi, zlo, zhi, P)


@njit(cache=True)
def prepare(x0, xref, uprev, P, xr, vlo, vhi, zlo, zhi):
    """Input checks, heading unwrapping, speed tube and input boxes (``input_boxes``) shared by
    both solvers; returns a status code."""
    for i in range(4):
        if not math.isfinite(x0[i]):
            return ST_NONFINITE_STATE
    for i in range(4):
        if not math.isfinite(xref[i]):
            return ST_NONFINITE_REF
    for i in range(2):
        if not math.isfinite(uprev[i]):
            return ST_NONFINITE_UPREV
    for i in range(4):
        xr[i] = xref[i]
    # heading error wrapped: the reference heading is moved to the branch nearest psi_0
    xr[3] = x0[3] + wrap_angle(xref[3] - x0[3])
    N = vlo.size
    if not speed_tube(x0[2], N, P, vlo, vhi):
        return ST_INFEASIBLE
    input_boxes(x0, uprev, vlo, vhi, P, zlo, zhi)
    return ST_OK


@njit(cache=True)
def steer_bound_start(x0, xref, uprev, z_from, P, vlo, vhi, zlo, zhi, z, X):
    """The second start: the accelerations of z_from with the steering held at whichever
    bound (left or right) costs less after projection (with a steering rate bound, the
    projection turns that into a ramp to the bound as fast as allowed). It lies in the basin
    of the solutions that turn as hard as allowed, which a chain warm-started from its own
    smooth plans rarely reaches (docs/mpc.md, "Two starts"). Returns that bound."""
    N = z.size // 2
    best = np.inf
    bound = P[P_DMAX]
    zc = np.empty(2 * N)
    for side in range(2):
        dval = P[P_DMAX] if side == 0 else P[P_DMIN]
        for k in range(N):
            zc[2 * k] = z_from[2 * k]
            zc[2 * k + 1] = dval
        project(zc, x0[2], vlo, vhi, zlo, zhi, P)
        rollout(x0, zc, P, X)
        Jc = cost_of(X, zc, xref, uprev, P)
        if Jc < best:
            best = Jc
            bound = dval
            z[:] = zc
    return bound


@njit(cache=True)
def second_start_pays(z, X, xref, new_ref, zlo, zhi, P):
    """The gate of the second start (constants _GATE_*): True when the first solution z
    (states X) keeps the steering saturated over a large share of the horizon and either the
    reference is new or the predicted path passes the reference point early. A step is
    saturated when delta_k is on its bound (zlo/zhi) or, with a steering rate bound, moves
    from delta_{k-1} at the full rate: the turn as hard as allowed."""
    N = z.size // 2
    rate = P[P_STEER_RATE] * P[P_DT]
    on = 0
    for k in range(N):
        d = z[2 * k + 1]
        sat = d >= zhi[2 * k + 1] - _STEER_ON_BOUND or d <= zlo[2 * k + 1] + _STEER_ON_BOUND
        if rate > 0.0 and k > 0 and abs(d - z[2 * k - 1]) >= rate - _STEER_ON_BOUND:
            sat = True
        if sat:
            on += 1
    if on * _GATE_SAT_DEN < _GATE_SAT_NUM * N:
        return False
    if new_ref:
        return True
    if on * _GATE_SAT_DEN < _GATE_PASS_NUM * N:
        return False
    kmin = 0
    dmin = np.inf
    for k in range(N + 1):
        dd = (X[k, 0] - xref[0]) ** 2 + (X[k, 1] - xref[1]) ** 2
        if dd < dmin:
            dmin = dd
            kmin = k
    return kmin * _GATE_KMIN_DEN <= _GATE_KMIN_NUM * N


@njit(cache=True)
def second_start_explores(z, bound):
    """The side rule of the gate (fast.steer_bound_other_side): True when the steering bound
    the second start holds lies on the other side of the first solution z's final steering
    angle (or that angle is zero). The second start is there to reach the basin of the
    turn as hard as allowed to one side; a first solution that already ends steering to that
    side lies in that basin, and a second start towards it converges back to the same plan
    (docs/mpc.md, "Two starts")."""
    return z[z.size - 1] * bound <= 0.0


@njit(cache=True)
def solve_slot(bi, X0, Xref, Uprev, Uwarm, has_warm, Rprev, guesses, P, max_iter, qp_max_iter,
               Uout, Xout, cost, status, iters, starts):
    """Problem bi of a batch: checks, one or two starts (the second behind its gate and side
    rule; the cheaper converged result is kept), warm start and fallback. Rprev[bi] is the
    reference of the slot's previous solve (the gate's "new reference"). Touches only slot bi
    of every array, so slots can run on different threads."""
    N = Uwarm.shape[1]
    n = 2 * N
    x0 = X0[bi]
    uprev = Uprev[bi]
    X = Xout[bi]
    xr = np.empty(4)
    vlo = np.empty(N)
    vhi = np.empty(N)
    zlo = np.empty(n)
    zhi = np.empty(n)
    z = np.empty(n)
    st = prepare(x0, Xref[bi], uprev, P, xr, vlo, vhi, zlo, zhi)
    new_ref = not has_warm[bi]
    for i in range(4):
        if Xref[bi, i] != Rprev[bi, i]:
            new_ref = True
        Rprev[bi, i] = Xref[bi, i]
    it = 0
    J = np.nan
    starts[bi] = 0
    if st == ST_OK:
        starts[bi] = 1
        initial_guess(x0, xr, uprev, Uwarm[bi], has_warm[bi], guesses, P, vlo, vhi, zlo, zhi, z, X)
        wk = sqp_workspace(N, P)
        build_constraints(x0[2], vlo, vhi, zlo, zhi, P, wk[5], wk[6])
        st, J, it = sqp_ws(x0, xr, uprev, z, P, max_iter, qp_max_iter, vlo, vhi, zlo, zhi, X, wk, np.inf)
        if P[P_STEER_START] > 0.5 and max_iter > 0 and (
                st != ST_OK or P[P_STEER_GATE] < 0.5 or second_start_pays(z, X, xr, new_ref, zlo, zhi, P)):
            z2 = np.empty(n)
            bound = steer_bound_start(x0, xr, uprev, z, P, vlo, vhi, zlo, zhi, z2, X)
            if st != ST_OK or P[P_STEER_GATE] < 0.5 or P[P_OTHER_SIDE] < 0.5 or second_start_explores(z, bound):
                starts[bi] = 2
                st2, J2, it2 = sqp_ws(x0, xr, uprev, z2, P, max_iter, qp_max_iter, vlo, vhi, zlo, zhi, X, wk,
                                      J if st == ST_OK else np.inf)
                it += it2
                if st2 == ST_OK and (st != ST_OK or J2 < J - _SAME_MINIMUM * (1.0 + abs(J))):
                    st = st2
                    z[:] = z2
    if st == ST_OK:
        project(z, x0[2], vlo, vhi, zlo, zhi, P)
        rollout(x0, z, P, X)
        J = cost_of(X, z, xr, uprev, P)
        finite = math.isfinite(J)
        for k in range(N):
            if not (math.isfinite(z[2 * k]) and math.isfinite(z[2 * k + 1])):
                finite = False
        if not finite:
            st = ST_NONFINITE_RESULT
    if st == ST_OK:
        for k in range(N):
            Uout[bi, k, 0] = z[2 * k]
            Uout[bi, k, 1] = z[2 * k + 1]
            Uwarm[bi, k, 0] = z[2 * k]
            Uwarm[bi, k, 1] = z[2 * k + 1]
        has_warm[bi] = True
    else:
        u = np.empty(2)
        fallback(x0, uprev, P, u)
        for k in range(N):
            Uout[bi, k, 0] = u[0]
            Uout[bi, k, 1] = u[1]
        has_warm[bi] = False
        finite_x0 = True
        for i in range(4):
            if not math.isfinite(x0[i]):
                finite_x0 = False
        if finite_x0:
            for k in range(N):
                z[2 * k] = u[0]
                z[2 * k + 1] = u[1]
            rollout(x0, z, P, X)
        else:
            X[:, :] = np.nan
        J = np.nan
    cost[bi] = J
    status[bi] = st
    iters[bi] = it


@njit(cache=True)
def solve_batch_kernel(X0, Xref, Uprev, Uwarm, has_warm, Rprev, guesses, P, max_iter, qp_max_iter,
                       Uout, Xout, cost, status, iters, starts):
    """B independent problems on the calling thread; Uwarm/has_warm are the per-slot warm starts (updated here)."""
    for bi in range(X0.shape[0]):
        solve_slot(bi, X0, Xref, Uprev, Uwarm, has_warm, Rprev, guesses, P, max_iter, qp_max_iter,
                   Uout, Xout, cost, status, iters, starts)


@njit(cache=True, parallel=True)
def solve_batch_parallel(X0, Xref, Uprev, Uwarm, has_warm, Rprev, guesses, P, max_iter, qp_max_iter,
                         Uout, Xout, cost, status, iters, starts):
    """As solve_batch_kernel, with the slots spread over numba's threads (they share only
    read-only inputs); the same solve_slot runs, so the results are the serial ones."""
    for bi in prange(X0.shape[0]):
        solve_slot(bi, X0, Xref, Uprev, Uwarm, has_warm, Rprev, guesses, P, max_iter, qp_max_iter,
                   Uout, Xout, cost, status, iters, starts)
