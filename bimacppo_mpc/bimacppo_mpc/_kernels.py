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
* each QP is solved exactly by a primal active-set method in the null space of its working
  set, warm-started with the previous working set. In the coordinates of the speed and
  steering profiles every constraint row is a bound on one profile value or on the difference
  of two neighbours, so a working set splits each profile into chains, the basis of its null
  space is one 0/1 interval per free chain, and the reduced Hessian is n_free x n_free
  (``qp_null_space``); the convexification acts on that reduced Hessian only
  (``factor_reduced``);
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
import llvmlite.ir as ir
from numba import njit, prange, types
from numba.extending import intrinsic

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
# factors, is below this share of the tolerance (converged_after_step): a margin of 10 for
# the Hessian's change over the step, so the estimate says yes only where the QP would (this
# close to the optimum the estimate and the next QP's decrease agree to a few per cent)
_EARLY_STOP_MARGIN = 1e-1
# ... and it does not try after a step whose QP predicted a decrease above this share of 1 + J:
# that far from the optimum the next QP hardly ever stops (the test would only cost time; on
# the benchmark's problems this skips 41 % of the tests and 5 of 1,044 early stops)
_EARLY_STOP_SKIP = 1e-3


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
def stage_trig(X, z, T):
    """T[k] = cos and sin of the course psi_k + delta_k and of the steering delta_k, stage by
    stage: what every derivative of the Euler step is made of. Computed once per point and
    read by the sensitivities, the gradient and the Hessian, which otherwise spend most of
    their time in these calls."""
    N = z.size // 2
    for k in range(N):
        d = z[2 * k + 1]
        psi = X[k, 3]
        T[k, 0] = math.cos(psi + d)
        T[k, 1] = math.sin(psi + d)
        T[k, 2] = math.cos(d)
        T[k, 3] = math.sin(d)


@njit(cache=True)
def step_jacobian(v, c, s, cd, sd, dt, L):
    """The nonzero entries of the Euler step's Jacobians at a stage with speed v, course cosine
    and sine c, s and steering cosine and sine cd, sd (stage_trig): A = d x_{k+1} / d x_k is the
    identity plus (a02, a03, a12, a13, a32) in the state order [x, y, v, psi]; B = d x_{k+1} / d u_k
    has dt at (v, a) and the steering column (a03, a13, 0, b31). Scalars in and out, so the
    callers' loops over the stages pay no call."""
    return dt * c, -dt * v * s, dt * s, dt * v * c, dt * 2.0 / L * sd, dt * 2.0 * v / L * cd


@njit(cache=True)
def gradient(x0, z, xref, uprev, P, X, T, lam, g):
    """The cost's gradient at z by one backward (adjoint) pass, X = rollout(x0, z) and
    T = stage_trig(X, z): the same derivative as ``derivatives``' g in O(N) instead of through
    the O(N^2) sensitivities."""
    N = z.size // 2
    L = P[P_L]
    dt = P[P_DT]
    for i in range(4):
        lam[N, i] = 2.0 * P[P_QX + i] * (X[N, i] - xref[i])
    for k in range(N - 1, -1, -1):
        a02, a03, a12, a13, a32, b31 = step_jacobian(X[k, 2], T[k, 0], T[k, 1], T[k, 2], T[k, 3], dt, L)
        l0 = lam[k + 1, 0]
        l1 = lam[k + 1, 1]
        l2 = lam[k + 1, 2]
        l3 = lam[k + 1, 3]
        # g_u = B' lam_{k+1}; lam_k = A' lam_{k+1} + the stage's tracking gradient
        g[2 * k] = dt * l2
        g[2 * k + 1] = a03 * l0 + a13 * l1 + b31 * l3
        if k > 0:
            lam[k, 0] = l0 + 2.0 * P[P_QX] * (X[k, 0] - xref[0])
            lam[k, 1] = l1 + 2.0 * P[P_QX + 1] * (X[k, 1] - xref[1])
            lam[k, 2] = l2 + a02 * l0 + a12 * l1 + a32 * l3 + 2.0 * P[P_QX + 2] * (X[k, 2] - xref[2])
            lam[k, 3] = l3 + a03 * l0 + a13 * l1 + 2.0 * P[P_QX + 3] * (X[k, 3] - xref[3])
    for k in range(N):
        for i in range(2):
            j = 2 * k + i
            u = z[j]
            up = uprev[i] if k == 0 else z[j - 2]
            g[j] += 2.0 * P[P_QU + i] * u + 2.0 * P[P_QDU + i] * (u - up)
            if k + 1 < N:
                g[j] -= 2.0 * P[P_QDU + i] * (z[j + 2] - u)


@njit(cache=True)
def derivatives(x0, z, xref, uprev, P, exact, X, T, S, lam, g, H):
    """Cost, gradient and (exact or Gauss-Newton) Hessian of the single-shooting cost; X, T, S
    and lam keep the rollout, its stage_trig, the forward sensitivities and the costates at z,
    which ``hessian(..., False, ...)`` reuses for the Gauss-Newton Hessian where it is needed.

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
    stage_trig(X, z, T)
    # forward sensitivities: S[k] = dx_k/dz; columns >= 2k are zero and never written, so S
    # must come zeroed (sqp_workspace's is)
    for k in range(N):
        a02, a03, a12, a13, a32, b31 = step_jacobian(X[k, 2], T[k, 0], T[k, 1], T[k, 2], T[k, 3], dt, L)
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
        S[k + 1, 0, 2 * k + 1] = a03
        S[k + 1, 1, 2 * k + 1] = a13
        S[k + 1, 2, 2 * k + 1] = 0.0
        S[k + 1, 3, 2 * k + 1] = b31
    # gradient and costates lam[k] = d(cost of x_k..x_N)/dx_k
    gradient(x0, z, xref, uprev, P, X, T, lam, g)
    hessian(z, X, T, S, lam, P, exact, H)
    return J


@njit(cache=True)
def hessian(z, X, T, S, lam, P, curv, Hm):
    """The single-shooting cost's Hessian at z into Hm: exact (curv: the tracking weights plus
    the costate-weighted curvature of the Euler step) or its Gauss-Newton part (the weights
    alone, always positive definite), from the rollout X, its stage_trig T, sensitivities S and
    costates lam that ``derivatives`` left at z (see its docstring for the recursion).

    The Euler step's Jacobians are the identity plus five entries (A) and four entries (B), and
    P_{k+1} is symmetric: the small products are written out over those entries in scalars,
    each sum in the order of the dense product, so the result is the dense recursion's bit for
    bit at a fraction of its memory traffic."""
    N = z.size // 2
    n = 2 * N
    L = P[P_L]
    dt = P[P_DT]
    q0 = 2.0 * P[P_QX]
    q1 = 2.0 * P[P_QX + 1]
    q2 = 2.0 * P[P_QX + 2]
    q3 = 2.0 * P[P_QX + 3]
    # P_{k+1}, symmetric: p_rq = p_qr
    p00 = q0
    p01 = 0.0
    p02 = 0.0
    p03 = 0.0
    p11 = q1
    p12 = 0.0
    p13 = 0.0
    p22 = q2
    p23 = 0.0
    p33 = q3
    for k in range(N - 1, -1, -1):
        v = X[k, 2]
        c = T[k, 0]
        s = T[k, 1]
        cd = T[k, 2]
        sd = T[k, 3]
        a02, a03, a12, a13, a32, b31 = step_jacobian(v, c, s, cd, sd, dt, L)
        b20 = dt
        b01 = a03
        b11 = a13
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
            m_vd = m_vp + lp * dt * 2.0 / L * cd
            m_dd = m_pp - lp * dt * 2.0 * v / L * sd
        # PB = P_{k+1} B (B's nonzeros: b20, b01, b11, b31)
        pb00 = p02 * b20
        pb10 = p12 * b20
        pb20 = p22 * b20
        pb30 = p23 * b20
        pb01 = p00 * b01 + p01 * b11 + p03 * b31
        pb11 = p01 * b01 + p11 * b11 + p13 * b31
        pb21 = p02 * b01 + p12 * b11 + p23 * b31
        pb31 = p03 * b01 + p13 * b11 + p33 * b31
        r0 = 2 * k
        Hm[r0, r0] = b20 * pb20
        Hm[r0 + 1, r0] = b01 * pb00 + b11 * pb10 + b31 * pb30
        Hm[r0 + 1, r0 + 1] = b01 * pb01 + b11 * pb11 + b31 * pb31 + m_dd
        # Kx = C^xu + A' P B
        k00 = pb00
        k10 = pb10
        k20 = a02 * pb00 + a12 * pb10 + pb20 + a32 * pb30
        k30 = a03 * pb00 + a13 * pb10 + pb30
        k01 = pb01
        k11 = pb11
        k21 = a02 * pb01 + a12 * pb11 + pb21 + a32 * pb31 + m_vd
        k31 = a03 * pb01 + a13 * pb11 + pb31 + m_pp
        for j in range(r0):
            s0 = S[k, 0, j]
            s1 = S[k, 1, j]
            s2 = S[k, 2, j]
            s3 = S[k, 3, j]
            Hm[r0, j] = s0 * k00 + s1 * k10 + s2 * k20 + s3 * k30
            Hm[r0 + 1, j] = s0 * k01 + s1 * k11 + s2 * k21 + s3 * k31
        if k > 0:
            # PA = P_{k+1} A (A = I + a02, a03, a12, a13, a32)
            pa02 = p00 * a02 + p01 * a12 + p02 + p03 * a32
            pa12 = p01 * a02 + p11 * a12 + p12 + p13 * a32
            pa22 = p02 * a02 + p12 * a12 + p22 + p23 * a32
            pa32 = p03 * a02 + p13 * a12 + p23 + p33 * a32
            pa03 = p00 * a03 + p01 * a13 + p03
            pa13 = p01 * a03 + p11 * a13 + p13
            pa33 = p03 * a03 + p13 * a13 + p33
            # P_k = C^xx + A' P A; PA's columns 0, 1 are P's
            n00 = p00 + q0
            n01 = p01
            n02 = p02
            n03 = p03
            n11 = p11 + q1
            n12 = p12
            n13 = p13
            n22 = a02 * pa02 + a12 * pa12 + pa22 + a32 * pa32 + q2
            n23 = a03 * pa02 + a13 * pa12 + pa32 + m_vp
            n33 = a03 * pa03 + a13 * pa13 + pa33 + q3 + m_pp
            # column r = 2, 3 with q = 0, 1: A[:, r]' PA[:, q] = A[:, r]' P[:, q]
            n02 = a02 * p00 + a12 * p01 + p02 + a32 * p03
            n12 = a02 * p01 + a12 * p11 + p12 + a32 * p13
            n03 = a03 * p00 + a13 * p01 + p03
            n13 = a03 * p01 + a13 * p11 + p13
            p00 = n00
            p01 = n01
            p02 = n02
            p03 = n03
            p11 = n11
            p12 = n12
            p13 = n13
            p22 = n22
            p23 = n23
            p33 = n33
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
    """Lower Cholesky of A[:m,:m] (its lower triangle is all it reads) into Lc; False if a pivot
    is <= min_pivot (not safely PD).

    Column j's entries below the diagonal are formed four rows at a time: four independent
    sums instead of one chain of dependent subtractions, each still summed in the order of k."""
    for j in range(m):
        s = A[j, j]
        for k in range(j):
            s -= Lc[j, k] * Lc[j, k]
        if s <= min_pivot or s <= _EPS_PIVOT * abs(A[j, j]):
            return False
        d = math.sqrt(s)
        Lc[j, j] = d
        i = j + 1
        while i + 3 < m:
            t0 = A[i, j]
            t1 = A[i + 1, j]
            t2 = A[i + 2, j]
            t3 = A[i + 3, j]
            for k in range(j):
                ljk = Lc[j, k]
                t0 -= Lc[i, k] * ljk
                t1 -= Lc[i + 1, k] * ljk
                t2 -= Lc[i + 2, k] * ljk
                t3 -= Lc[i + 3, k] * ljk
            Lc[i, j] = t0 / d
            Lc[i + 1, j] = t1 / d
            Lc[i + 2, j] = t2 / d
            Lc[i + 3, j] = t3 / d
            i += 4
        while i < m:
            t = A[i, j]
            for k in range(j):
                t -= Lc[i, k] * Lc[j, k]
            Lc[i, j] = t / d
            i += 1
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


# ---------------------------------------------------------------------------------------------
# The QP in the profile coordinates. A step p of the inputs is a step q of the profiles
# (q[2k] = change of v_{k+1}, q[2k+1] = change of delta_k; p[2k] = (q[2k] - q[2k-2]) / dt with
# q[-2] = 0, since v_0 is measured). In q every row of build_constraints is a bound on one value
# (speed tube, steering box, the first acceleration's box: a "fix" row) or on the difference of
# two neighbours (acceleration box, steering rate: a "link" row). A working set therefore splits
# each channel's positions 0..N-1 into chains joined by its link rows; a chain holding a fix row
# is fixed, every other one moves as a whole. The working set's null space is spanned by one
# interval indicator per free chain (in p: +1/dt and -1/dt at the ends of a speed interval, ones
# over a steering interval), a row is dependent exactly when it would join two fixed chains or
# fix a fixed one, and the multipliers follow by summing the residual along each chain. So the
# QP works on the reduced Hessian Z'Hc Z of the free chains (about half of n at the closed-loop
# optimum, where the steering ramps at its rate bound or rests on its box) instead of the n x n
# Hessian and a Schur complement of every active row.
# ---------------------------------------------------------------------------------------------
@njit(cache=True)
def row_shape(c, N, dt):
    """Row c of build_constraints in the profile coordinates q: (channel, position k, link, coef).
    A link row is coef * (q_ch[k] - q_ch[k-1]), a fix row coef * q_ch[k]; channel 0 is the speed
    (position k = v_{k+1}), 1 the steering (position k = delta_k)."""
    n = 2 * N
    if c >= 6 * N:
        j = c - 6 * N
        if j >= N - 1:
            return 1, j - (N - 1) + 1, True, -1.0
        return 1, j + 1, True, 1.0
    if c >= 2 * n:
        k = c - 2 * n
        if k >= N:
            return 0, k - N, False, -1.0
        return 0, k, False, 1.0
    sign = 1.0
    if c >= n:
        c -= n
        sign = -1.0
    k = c // 2
    if c % 2 == 1:
        return 1, k, False, sign
    if k == 0:
        return 0, 0, False, sign / dt
    return 0, k, True, sign / dt


@njit(cache=True)
def add_rows(rows, nrows, N, dt, link, fix, check):
    """Enter rows[:nrows], in order, into the chain structure (link, fix): with check, each row
    only if it is independent of those already there, i.e. it neither fixes a chain that holds
    a fix row nor links two such chains (without check every row is entered: a working set
    already known to be independent). The rows entered are moved to the front of rows, in
    order; returns their number. The chain walks are written out here rather than called per
    row: in the compiled kernels a call with array arguments costs more than a row's walk."""
    kept = 0
    for a in range(nrows):
        c = rows[a]
        ch, k, is_link, coef = row_shape(c, N, dt)
        base = ch * N
        if check:
            # a link row joins the chain ending at k - 1 to the one starting at k (dependent when
            # both hold a fix row); a fix row fixes the chain through k (dependent when it already
            # holds one). Walk left from jl, then, unless that decided it, right from k.
            if is_link:
                if link[base + k] >= 0:
                    continue
                jl = k - 1
            else:
                jl = k
            fixed = False
            j = jl
            step = -1
            for side in range(2):
                while True:
                    if fix[base + j] >= 0:
                        fixed = True
                        break
                    nb = j if step < 0 else j + 1      # the link to the next position this way
                    if nb == 0 or nb >= N or link[base + nb] < 0:
                        break
                    j += step
                if side == 0:
                    if fixed != is_link:               # a fixed part for a fix row, a free one for a link
                        break
                    fixed = False
                    j = k
                    step = 1
            if fixed:
                continue
        if is_link:
            link[base + k] = c
        else:
            fix[base + k] = c
        rows[kept] = c
        kept += 1
    return kept


@njit(cache=True)
def hz_columns(H, N, dt, iv, c0, c1, M):
    """M[:, c] = H z for the basis columns c0 <= c < c1, from their intervals iv (steering: the
    sum of H's columns over the interval; speed: two columns scaled by +-1/dt). One call for a
    run of columns: a call with array arguments costs more than a column's arithmetic."""
    n = 2 * N
    idt = 1.0 / dt
    for c in range(c0, c1):
        ch = iv[c, 0]
        lo = iv[c, 1]
        hi = iv[c, 2]
        if ch == 1:
            for i in range(n):
                t = 0.0
                for j in range(lo, hi + 1):
                    t += H[i, 2 * j + 1]
                M[i, c] = t
        elif hi + 1 < N:
            for i in range(n):
                M[i, c] = (H[i, 2 * lo] - H[i, 2 * (hi + 1)]) * idt
        else:
            for i in range(n):
                M[i, c] = H[i, 2 * lo] * idt


@njit(cache=True)
def move_flags(N, lab, m, mv):
    """mv[c]: whether row c changes along the basis of the free chains (labels lab), for every
    row of build_constraints, read off its structure."""
    n = 2 * N
    for k in range(N):
        a = lab[2 * k] >= 0 if k == 0 else lab[2 * (k - 1)] != lab[2 * k]
        d = lab[2 * k + 1] >= 0
        mv[2 * k] = a
        mv[n + 2 * k] = a
        mv[2 * k + 1] = d
        mv[n + 2 * k + 1] = d
        v = lab[2 * k] >= 0
        mv[2 * n + k] = v
        mv[2 * n + N + k] = v
    if m > 6 * N:
        for k in range(1, N):
            r = lab[2 * (k - 1) + 1] != lab[2 * k + 1]
            mv[6 * N + k - 1] = r
            mv[7 * N - 1 + k - 1] = r


@njit(cache=True)
def interval_columns(N, dt, iv, c0, c1, colptr, zidx, zval):
    """The entries of basis columns c0 <= c < c1 in the inputs from their q intervals iv
    (channel, first, last): ones over a steering interval; +1/dt and -1/dt on the accelerations
    that begin and end a speed interval. Written from colptr[c0] on; sets colptr[c0 + 1:c1 + 1]."""
    nnz = colptr[c0]
    for c in range(c0, c1):
        ch = iv[c, 0]
        lo = iv[c, 1]
        hi = iv[c, 2]
        if ch == 1:
            for j in range(lo, hi + 1):
                zidx[nnz] = 2 * j + 1
                zval[nnz] = 1.0
                nnz += 1
        else:
            zidx[nnz] = 2 * lo
            zval[nnz] = 1.0 / dt
            nnz += 1
            if hi + 1 < N:
                zidx[nnz] = 2 * (hi + 1)
                zval[nnz] = -1.0 / dt
                nnz += 1
        colptr[c + 1] = nnz


@njit(cache=True)
def chain_runs(N, link, fix, runs):
    """The chains of the working set's structure, channel by channel from position 0: runs[r] =
    (channel, first, last, the position of its fix row or -1). Returns their number."""
    nr = 0
    for ch in range(2):
        k = 0
        while k < N:
            e = k
            while e + 1 < N and link[ch * N + e + 1] >= 0:
                e += 1
            f = -1
            for j in range(k, e + 1):
                if fix[ch * N + j] >= 0:
                    f = j
            runs[nr, 0] = ch
            runs[nr, 1] = k
            runs[nr, 2] = e
            runs[nr, 3] = f
            nr += 1
            k = e + 1
    return nr


@njit(cache=True)
def chain_basis(N, dt, link, fix, lab, colptr, zidx, zval, iv, runs):
    """Columns of the null-space basis in z: one per free chain (runs: chain_runs' buffer).
    Returns their number."""
    nf = 0
    for r in range(chain_runs(N, link, fix, runs)):
        ch = runs[r, 0]
        k = runs[r, 1]
        e = runs[r, 2]
        if runs[r, 3] >= 0:
            for j in range(k, e + 1):
                lab[2 * j + ch] = -1
        else:
            for j in range(k, e + 1):
                lab[2 * j + ch] = nf
            iv[nf, 0] = ch
            iv[nf, 1] = k
            iv[nf, 2] = e
            nf += 1
    colptr[0] = 0
    interval_columns(N, dt, iv, 0, nf, colptr, zidx, zval)
    return nf


@njit(cache=True)
def reduced_hessian(H, G, N, dt, link, fix, lab, colptr, zidx, zval, iv, runs, M, Hb, R, ZtZ, A, nA, inW, w):
    """Basis of the working set's null space, M = H Z, Hb = Z'HZ, R = sum over moving active rows
    outside W of w w' (w = G_i Z), ZtZ = Z'Z. Returns nf."""
    nf = chain_basis(N, dt, link, fix, lab, colptr, zidx, zval, iv, runs)
    hz_columns(H, N, dt, iv, 0, nf, M)
    # row c1 of Hb = the sum over column c1's entries of zval * (that row of M), entry by entry
    # in the order of the entries: whole rows at a time, in contiguous memory
    for c1 in range(nf):
        for c2 in range(c1 + 1):
            Hb[c1, c2] = 0.0
            R[c1, c2] = 0.0
            ZtZ[c1, c2] = 0.0
        for q in range(colptr[c1], colptr[c1 + 1]):
            zq = zval[q]
            r = zidx[q]
            for c2 in range(c1 + 1):
                Hb[c1, c2] += zq * M[r, c2]
    # Z'Z: columns overlap only where a speed chain ends and the next begins
    for c in range(nf):
        t = 0.0
        for q in range(colptr[c], colptr[c + 1]):
            t += zval[q] * zval[q]
        ZtZ[c, c] = t
    for k in range(1, N):
        a = lab[2 * (k - 1)]
        b2 = lab[2 * k]
        if a >= 0 and b2 >= 0 and a != b2:
            # z index 2k is -1/dt in chain a (ends at k-1) and +1/dt in chain b2 (starts at k)
            hi = max(a, b2)
            lo = min(a, b2)
            ZtZ[hi, lo] -= 1.0 / (dt * dt)
    for j in range(nA):
        c = A[j]
        if inW[c]:
            continue
        ch, k, is_link, coef = row_shape(c, N, dt)
        for i in range(nf):
            w[i] = 0.0
        l1 = lab[2 * k + ch]
        if l1 >= 0:
            w[l1] += coef
        if is_link:
            l0 = lab[2 * (k - 1) + ch]
            if l0 >= 0:
                w[l0] -= coef
        for c1 in range(nf):
            if w[c1] == 0.0:
                continue
            for c2 in range(c1 + 1):
                R[c1, c2] += w[c1] * w[c2]
    return nf


@njit(cache=True)
def _assemble_reduced(Hr, Hb, R, ZtZ, nf, rho, tau):
    for c1 in range(nf):
        for c2 in range(c1 + 1):
            t = Hb[c1, c2] + rho * R[c1, c2] + tau * ZtZ[c1, c2]
            Hr[c1, c2] = t
            Hr[c2, c1] = t


@njit(cache=True)
def factor_reduced(Hr, Hb, R, ZtZ, Lr, Lsp, nf, dmax, cv):
    """Factor Z'(H + rho sum G_i'G_i + tau I)Z, raising rho (0, then dmax * 10^t, t < _RHO_TRIES)
    and then tau (smallest found by trials x8 and bisection) until it is positive definite.
    cv[:2] = [rho, tau]. Returns False if no shift up to dmax works."""
    min_pivot = _MIN_PIVOT * dmax
    rho = cv[0]
    tau = cv[1]
    while True:
        if rho == 0.0 and tau == 0.0:
            # no convexification: the matrix is Hb itself (cholesky reads the lower triangle)
            if cholesky(Hb, Lr, nf, min_pivot):
                break
        else:
            _assemble_reduced(Hr, Hb, R, ZtZ, nf, rho, tau)
            if cholesky(Hr, Lr, nf, min_pivot):
                break
        has_r = False
        for c in range(nf):
            if R[c, c] != 0.0:
                has_r = True
        if tau == 0.0 and has_r and rho < dmax * _RHO_GROWTH ** (_RHO_TRIES - 1):
            rho = dmax if rho == 0.0 else rho * _RHO_GROWTH
            continue
        hi = _SHIFT0 * dmax if tau == 0.0 else tau * _SHIFT_GROWTH
        while True:
            _assemble_reduced(Hr, Hb, R, ZtZ, nf, rho, hi)
            if cholesky(Hr, Lr, nf, min_pivot):
                break
            hi *= _SHIFT_GROWTH
            if hi > dmax:
                return False
        lo = hi / _SHIFT_GROWTH
        for _ in range(_SHIFT_BISECT):
            mid = math.sqrt(lo * hi)
            _assemble_reduced(Hr, Hb, R, ZtZ, nf, rho, mid)
            if cholesky(Hr, Lsp, nf, min_pivot):
                hi = mid
                for i in range(nf):
                    for j in range(nf):
                        Lr[i, j] = Lsp[i, j]
            else:
                lo = mid
        tau = hi
        break
    cv[0] = rho
    cv[1] = tau
    return True


@njit(cache=True)
def hc_product(H, G, A, nA, rho, tau, x, out):
    """out = Hc x with Hc = H + rho * sum over the active rows A of G_i'G_i + tau * I, the
    convexified Hessian of the QP (``factor_reduced``)."""
    n = H.shape[0]
    for i in range(n):
        t = 0.0
        for k in range(n):
            t += H[i, k] * x[k]
        out[i] = t + tau * x[i]
    if rho > 0.0:
        for j in range(nA):
            c = A[j]
            t = 0.0
            for i in range(n):
                t += G[c, i] * x[i]
            if t != 0.0:
                for i in range(n):
                    out[i] += rho * t * G[c, i]


@njit(cache=True)
def working_set_multipliers(r, N, dt, link, fix, lamr, rq, runs):
    """lamr[c] for every row c of the working set (links and fixes) with G_W' lam = r (runs:
    chain_runs' buffer)."""
    for k in range(N):
        nxt = r[2 * k + 2] if k + 1 < N else 0.0
        rq[2 * k] = (r[2 * k] - nxt) / dt
        rq[2 * k + 1] = r[2 * k + 1]
    for q in range(chain_runs(N, link, fix, runs)):
        ch = runs[q, 0]
        k = runs[q, 1]
        e = runs[q, 2]
        f = runs[q, 3]
        last = e if f < 0 else f
        # from the left end: phi_{j+1} = phi_j - rq[j]
        phi = 0.0
        for j in range(k, last):
            phi = phi - rq[2 * j + ch]
            c = link[ch * N + j + 1]
            _, _, _, coef = row_shape(c, N, dt)
            lamr[c] = phi / coef
        phi_left = phi
        if f >= 0:
            phi = 0.0
            for j in range(e, f, -1):
                phi = rq[2 * j + ch] + phi
                c = link[ch * N + j]
                _, _, _, coef = row_shape(c, N, dt)
                lamr[c] = phi / coef
            cf = fix[ch * N + f]
            _, _, _, coef = row_shape(cf, N, dt)
            lamr[cf] = (rq[2 * f + ch] - phi_left + phi) / coef


@njit(cache=True)
def row_on_interval(c, N, dt, ch, lo, hi):
    """G_c z for the basis column of the q interval [lo, hi] of channel ch."""
    rch, k, is_link, coef = row_shape(c, N, dt)
    if rch != ch:
        return 0.0
    v = coef if lo <= k <= hi else 0.0
    if is_link and lo <= k - 1 <= hi:
        v -= coef
    return v


@njit(cache=True)
def reduced_row(c, N, dt, iv, w, nf):
    """w = Z' G_c' (the row in the basis); returns the index of its first nonzero (nf if none)."""
    first = nf
    for j in range(nf):
        w[j] = row_on_interval(c, N, dt, iv[j, 0], iv[j, 1], iv[j, 2])
        if w[j] != 0.0 and first == nf:
            first = j
    return first


@njit(cache=True)
def append_column(H, N, dt, ch, lo, hi, nf, colptr, zidx, zval, iv, M, A, nA, cv, Lr, dmax, zd, hcol):
    """Border the basis with the interval column [lo, hi] of channel ch: its entries, H z, its
    row of Z'Hc Z and the factor's new row. False if the bordered matrix is not safely positive
    definite (the caller rebuilds with more convexification)."""
    n = 2 * N
    iv[nf, 0] = ch
    iv[nf, 1] = lo
    iv[nf, 2] = hi
    interval_columns(N, dt, iv, nf, nf + 1, colptr, zidx, zval)
    nnz = colptr[nf + 1]
    hz_columns(H, N, dt, iv, nf, nf + 1, M)
    # the new row of Z'Hc Z: H part, tau z'z, rho over the active rows outside W
    for i in range(n):
        zd[i] = 0.0
    for k in range(colptr[nf], nnz):
        zd[zidx[k]] = zval[k]
    for j in range(nf + 1):
        t = 0.0
        tz = 0.0
        for k in range(colptr[j], colptr[j + 1]):
            t += zval[k] * M[zidx[k], nf]
            tz += zval[k] * zd[zidx[k]]
        hcol[j] = t + cv[1] * tz
    if cv[0] > 0.0:
        for a in range(nA):
            c = A[a]
            gn = row_on_interval(c, N, dt, ch, lo, hi)
            if gn == 0.0:
                continue
            for j in range(nf + 1):
                gj = row_on_interval(c, N, dt, iv[j, 0], iv[j, 1], iv[j, 2])
                hcol[j] += cv[0] * gn * gj
    # the factor's new row: l = Lr^-1 hcol[:nf], d = sqrt(h_nn - l'l)
    for i in range(nf):
        t = hcol[i]
        for k in range(i):
            t -= Lr[i, k] * Lr[nf, k]
        Lr[nf, i] = t / Lr[i, i]
    d2 = hcol[nf]
    for k in range(nf):
        d2 -= Lr[nf, k] * Lr[nf, k]
    if d2 <= _MIN_PIVOT * dmax or d2 <= _EPS_PIVOT * abs(hcol[nf]):
        return False
    Lr[nf, nf] = math.sqrt(d2)
    for i in range(nf):
        Lr[i, nf] = 0.0
    return True


@njit(cache=True)
def _chol_rank1(L, e, m):
    """L L' + e e' = L' L'' in place (e is overwritten)."""
    for k in range(m):
        lkk = L[k, k]
        r = math.hypot(lkk, e[k])
        c = r / lkk
        sn = e[k] / lkk
        L[k, k] = r
        for i in range(k + 1, m):
            L[i, k] = (L[i, k] + sn * e[i]) / c
            e[i] = c * e[i] - sn * L[i, k]


@njit(cache=True)
def _model_gradient(G, A, nA, N, cv, M, colptr, zidx, zval, nf, pr, gq, s):
    """gq += Hc Z pr (the model's gradient moved along the steps since the rebuild), pr = 0."""
    n = 2 * N
    for i in range(n):
        s[i] = 0.0
    for c in range(nf):
        for k in range(colptr[c], colptr[c + 1]):
            s[zidx[k]] += zval[k] * pr[c]
    for i in range(n):
        t = 0.0
        for c in range(nf):
            t += M[i, c] * pr[c]
        gq[i] += t + cv[1] * s[i]
    if cv[0] > 0.0:
        for j in range(nA):
            c = A[j]
            t = 0.0
            for i in range(n):
                t += G[c, i] * s[i]
            if t != 0.0:
                t *= cv[0]
                for i in range(n):
                    gq[i] += t * G[c, i]
    for c in range(nf):
        pr[c] = 0.0


@njit(cache=True)
def qp_null_space(H, g, G, b, W, nW, maxit, p, lamW, inW, dmax, dt, qk):
    """min 1/2 p'Hc p + g'p s.t. G p <= b, from the feasible p = 0 (b >= 0), with Hc the
    convexified Hessian H + rho * sum_A G_i'G_i + tau * I over the rows A active at p = 0
    (``factor_reduced`` picks rho and tau on the reduced Hessian).

    W[:nW] is the initial working set (rows still active and independent are kept, in order).
    The working set is W0 followed by W2: W0 is held by the chain structure and its null-space
    basis Z, whose reduced Hessian Z'Hc Z is factored (Lr) when W0 is built; rows that block a
    step join W2, handled by the Schur complement of their reduced rows against Lr (the range
    space of the reduced problem: ``_ws_append``, ``_ws_delete``); a W0 row that leaves adds the
    direction it frees to the basis as one more column of Z and row of Lr (``append_column``).
    So a factorisation happens once per QP unless the bordered factor loses positive
    definiteness, which rebuilds W0 from the whole working set with more convexification.

    q = Lr^-1 Z'(Hc p + g) is kept up to date from the steps (Lr' pr moves by -alpha r, r the
    projected residual), so an iteration needs no product with H. The
    model gradient gq = g + Hc p is formed where the multipliers need it and left in
    qk[13][0] for the SQP's predicted decrease. Returns (code, nW): 0 optimal (lamW holds the
    multipliers), 1 iteration limit or a numerically dependent blocking row (p feasible, not
    optimal), 2 no convexification with a shift up to max |H_ii| (the caller falls back to the
    Gauss-Newton Hessian)."""
    n = g.size
    N = n // 2
    m = b.size
    (link, fix, lab, colptr, zidx, zval, M, Hb, R, ZtZ, Lr, Hr, Lsp, ws, A, lamr, cv, Y2, Ls2, mv, iv,
     runs) = qk
    gq = ws[0]
    s = ws[1]
    sr = ws[2]
    gr = ws[3]
    yv = ws[4]
    Gs = ws[5]
    slack = ws[6]
    tmp = ws[7]
    q = ws[8]
    rr = ws[9]
    lam2 = ws[10]
    tmp2 = ws[11]
    qg = ws[12]       # Lr^-1 Z' gq at the last rebuild
    wr = ws[13]       # Lr' pr: Lr^-1 Z'(gq - gq at the rebuild), kept from the steps
    pr = ws[14]       # the step since the rebuild in the basis: p = p at the rebuild + Z pr
    cv[0] = 0.0
    cv[1] = 0.0
    for i in range(n):
        p[i] = 0.0
        gq[i] = g[i]
    nA = 0
    for c in range(m):
        inW[c] = False
        if b[c] > _EPS_ACTIVE:
            slack[c] = b[c]
        else:
            slack[c] = 0.0
            A[nA] = c
            nA += 1
    cv[2] = nA
    for i in range(2 * N):
        link[i] = -1
        fix[i] = -1
    n2 = 0
    for a in range(nW):
        c = W[a]
        if slack[c] <= 0.0:
            W[n2] = c
            n2 += 1
    nW = add_rows(W, n2, N, dt, link, fix, True)
    for a in range(nW):
        inW[W[a]] = True
    n0 = nW
    gnorm = 1.0
    for i in range(n):
        gnorm = max(gnorm, abs(g[i]))
    rebuild = True
    nf = 0
    for it in range(maxit):
        if rebuild:
            # W0 := the whole working set, W2 empty: a new basis and factor (at it = 0 link and
            # fix already hold exactly the working set)
            if it > 0:
                for i in range(2 * N):
                    link[i] = -1
                    fix[i] = -1
                add_rows(W, nW, N, dt, link, fix, False)
            n0 = nW
            nf = reduced_hessian(H, G, N, dt, link, fix, lab, colptr, zidx, zval, iv, runs, M, Hb, R, ZtZ, A, nA,
                                 inW, tmp)
            cv[3] = nf
            if not factor_reduced(Hr, Hb, R, ZtZ, Lr, Lsp, nf, dmax, cv):
                return 2, nW
            # the model's gradient at p under this basis' convexification (g itself at p = 0)
            if it > 0:
                hc_product(H, G, A, nA, cv[0], cv[1], p, tmp)
                for i in range(n):
                    gq[i] = g[i] + tmp[i]
            move_flags(N, lab, m, mv)
            for c in range(nf):
                t = 0.0
                for k in range(colptr[c], colptr[c + 1]):
                    t += zval[k] * gq[zidx[k]]
                gr[c] = t
                wr[c] = 0.0
                pr[c] = 0.0
            fwd_solve(Lr, gr, qg, nf)
            rebuild = False
        n2 = nW - n0
        for c in range(nf):
            q[c] = qg[c] + wr[c]
        _project_off(q, Y2, Ls2, n2, nf, tmp2, yv, lam2, rr)
        bwd_solve(Lr, rr, sr, nf)
        for i in range(n):
            s[i] = 0.0
        for c in range(nf):
            sc = -sr[c]
            sr[c] = sc
            for k in range(colptr[c], colptr[c + 1]):
                s[zidx[k]] += zval[k] * sc
        snorm = 0.0
        for i in range(n):
            snorm = max(snorm, abs(s[i]))
        alpha = 1.0
        block = -1
        if snorm > 0.0:
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
                if inW[c] or not mv[c]:
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
            for c in range(nf):
                pr[c] += alpha * sr[c]
                wr[c] -= alpha * rr[c]
            for c in range(m):
                if Gs[c] != 0.0:
                    slack[c] = max(slack[c] - alpha * Gs[c], 0.0)
        if block >= 0:
            slack[block] = 0.0
            first = reduced_row(block, N, dt, iv, tmp, nf)
            fwd_solve_from(Lr, tmp, yv, nf, first)
            nn = _ws_append(yv, first, Y2, Ls2, n2, nf, tmp2)
            if nn == n2:
                _model_gradient(G, A, nA, N, cv, M, colptr, zidx, zval, nf, pr, gq, s)
                return 1, nW
            W[nW] = block
            inW[block] = True
            nW += 1
            continue
        # full step: the working set's minimiser; W2's multipliers came with the projection,
        # W0's follow from the residual less W2's part by the chain walk
        _model_gradient(G, A, nA, N, cv, M, colptr, zidx, zval, nf, pr, gq, s)
        for i in range(n):
            tmp[i] = -gq[i]
        for a in range(n2):
            c = W[n0 + a]
            la = lam2[a]
            lamr[c] = la
            for i in range(n):
                tmp[i] -= la * G[c, i]
        working_set_multipliers(tmp, N, dt, link, fix, lamr, yv, runs)
        worst = -1
        wval = -_EPS_LAM * gnorm
        for a in range(nW):
            la = lamr[W[a]]
            if la < wval:
                wval = la
                worst = a
        if worst < 0:
            for a in range(nW):
                lamW[a] = lamr[W[a]]
            cv[4] = n0
            return 0, nW
        c = W[worst]
        inW[c] = False
        for a in range(worst, nW - 1):
            W[a] = W[a + 1]
        nW -= 1
        if worst >= n0:
            a2 = worst - n0
            for a in range(a2, n2 - 1):
                for i in range(nf):
                    Y2[a, i] = Y2[a + 1, i]
            _ws_delete(Ls2, n2, a2)
        else:
            # a W0 row leaves: the basis gains the direction it freed (an interval of one channel)
            n0 -= 1
            ch, k, is_link, coef = row_shape(c, N, dt)
            if is_link:
                link[ch * N + k] = -1
            else:
                fix[ch * N + k] = -1
            # the chain through k, or for a link the two it splits into, [lo, k-1] and [k, hi]
            lo = k - 1 if is_link else k
            while lo > 0 and link[ch * N + lo] >= 0:
                lo -= 1
            hi = k
            while hi + 1 < N and link[ch * N + hi + 1] >= 0:
                hi += 1
            if is_link:
                # the new direction moves the part that is free
                right_fixed = False
                for j in range(k, hi + 1):
                    if fix[ch * N + j] >= 0:
                        right_fixed = True
                if right_fixed:
                    hi = k - 1
                else:
                    lo = k
            _model_gradient(G, A, nA, N, cv, M, colptr, zidx, zval, nf, pr, gq, s)
            for j in range(nf):
                qg[j] += wr[j]
                wr[j] = 0.0
            if not append_column(H, N, dt, ch, lo, hi, nf, colptr, zidx, zval, iv, M, A, nA, cv, Lr,
                                 dmax, tmp, tmp2):
                rebuild = True
                continue
            dnew = Lr[nf, nf]
            t = 0.0
            for k2 in range(colptr[nf], colptr[nf + 1]):
                t += zval[k2] * gq[zidx[k2]]
            for j in range(nf):
                t -= Lr[nf, j] * qg[j]
            qg[nf] = t / dnew
            wr[nf] = 0.0
            pr[nf] = 0.0
            for a in range(n2):
                cw = W[n0 + a]
                t = row_on_interval(cw, N, dt, ch, lo, hi)
                for j in range(nf):
                    t -= Lr[nf, j] * Y2[a, j]
                t /= dnew
                Y2[a, nf] = t
                tmp2[a] = t
            _chol_rank1(Ls2, tmp2, n2)
            for c2 in range(m):
                if not mv[c2] and row_on_interval(c2, N, dt, ch, lo, hi) != 0.0:
                    mv[c2] = True
            nf += 1
            cv[3] = nf
    if not rebuild:
        _model_gradient(G, A, nA, N, cv, M, colptr, zidx, zval, nf, pr, gq, s)
    return 1, nW


@njit(cache=True)
def converged_after_step(x0, z, xref, uprev, P, X, T, J, h, G, W, nW, qk, lam, tol):
    """True when the next SQP iteration at the accepted full step z (states X, cost J) would
    stop at once: the QP's predicted decrease there is <= tol * (1 + J) with the same working
    set, estimated without a new Hessian.

    At z the working-set QP's first step is the reduced gradient Z' grad, solved against the
    last QP's factor Lr and projected off W2 (its Schur complement): decrease 1/2 |r|^2. Lr is
    the factor of the previous iterate's Hessian: after a full Newton step the two differ by the
    order of the step, so the estimate must be under _EARLY_STOP_MARGIN times the tolerance.
    The working set must still be active at z and the multipliers of that step's end point
    non-negative (W2's from the projection, W0's by the chain walk of the residual), or the
    next QP would move its working set. When the test holds, the next iteration would return z
    unchanged: the result is the same, one derivative evaluation, convexification and QP
    earlier."""
    n = z.size
    N = n // 2
    dt = P[P_DT]
    (link, fix, lab, colptr, zidx, zval, M, Hb, R, ZtZ, Lr, Hr, Lsp, ws, A, lamr, cv, Y2, Ls2, mv, iv,
     runs) = qk
    g = ws[0]
    s = ws[1]
    sr = ws[2]
    gr = ws[3]
    yv = ws[4]
    b = ws[6]
    tmp = ws[7]
    q = ws[8]
    rr = ws[9]
    lam2 = ws[10]
    tmp2 = ws[11]
    nf = int(cv[3])
    n0 = int(cv[4])
    n2 = nW - n0
    stage_trig(X, z, T)
    gradient(x0, z, xref, uprev, P, X, T, lam, g)
    slacks(z, h, dt, b)
    for a in range(nW):
        if b[W[a]] > _EPS_ACTIVE:
            return False
    gnorm = 1.0
    for i in range(n):
        gnorm = max(gnorm, abs(g[i]))
    for c in range(nf):
        t = 0.0
        for k in range(colptr[c], colptr[c + 1]):
            t += zval[k] * g[zidx[k]]
        gr[c] = t
    fwd_solve(Lr, gr, q, nf)
    _project_off(q, Y2, Ls2, n2, nf, tmp2, yv, lam2, rr)
    pred = 0.0
    for c in range(nf):
        pred += rr[c] * rr[c]
    pred *= 0.5
    if not pred <= _EARLY_STOP_MARGIN * tol * (1.0 + J):
        return False
    # the step's end: the model gradient g + Hc Z sr with sr = -Lr^-T r, from M = H Z
    bwd_solve(Lr, rr, sr, nf)
    for c in range(nf):
        sr[c] = -sr[c]
    for i in range(n):
        tmp[i] = g[i]
    _model_gradient(G, A, int(cv[2]), N, cv, M, colptr, zidx, zval, nf, sr, tmp, s)
    for i in range(n):
        tmp[i] = -tmp[i]
    for a in range(n2):
        c = W[n0 + a]
        lamr[c] = lam2[a]
        for i in range(n):
            tmp[i] -= lam2[a] * G[c, i]
    working_set_multipliers(tmp, N, dt, link, fix, lamr, yv, runs)
    for a in range(nW):
        if lamr[W[a]] < -_EPS_LAM * gnorm:
            return False
    return True


@njit(cache=True)
def sqp_workspace(N, P):
    """The arrays of one SQP (allocated once per problem and shared by its starts): the
    derivatives', the constraints (G = wk[5], h = wk[6]), the step and the working set, and the
    QP's (``qp_null_space``)."""
    n = 2 * N
    m = n_rows(N, P)
    # the QP's arrays, in order: link and fix (the W0 row at each channel position, -1: none),
    # lab (each q index's free chain, -1: fixed), colptr / zidx / zval (the basis columns' entries
    # in the inputs, room for every column a QP can append), M = H Z, Hb = Z'HZ, R (the released
    # active rows' w w'), ZtZ, Lr (the factor of Z'Hc Z), Hr and a spare factor (the shift search's
    # trials), 15 work vectors (ws[0]: the model gradient g + Hc p), A (the rows active at p = 0),
    # lamr (multipliers by row), cv = [rho, tau, |A|, n_f, |W0|], Y2 and
    # Ls2 (W2's reduced rows solved against Lr, the factor of their Gram matrix), mv (the rows
    # that move along Z), iv (each column's channel and interval) and runs (chain_runs' buffer)
    # Carved from three buffers (floats, integers, flags) rather than allocated one by one: the
    # allocations and frees of some forty arrays cost more than a Gauss-Newton step. The arrays
    # that must start at zero (or -1) are contiguous in their buffer and set in one pass.
    nz = n * N + 3 * N
    nn = n * n
    w = max(n, m)
    sz_s = (N + 1) * 4 * n
    sz_x = (N + 1) * 4
    F = np.empty(5 + nn + sz_s + sz_x + nz + 8 * nn + 15 * w + m + n + nn + m * n + 2 * m + 3 * n + sz_x + 4 * N)
    o = 5 + nn + sz_s + sz_x
    F[:o] = 0.0
    cv = F[0:5]
    Ls2 = F[5:5 + nn].reshape((n, n))
    S = F[5 + nn:5 + nn + sz_s].reshape((N + 1, 4, n))
    lam = F[o - sz_x:o].reshape((N + 1, 4))
    zval = F[o:o + nz]
    o += nz
    M = F[o:o + nn].reshape((n, n))
    Hb = F[o + nn:o + 2 * nn].reshape((n, n))
    R = F[o + 2 * nn:o + 3 * nn].reshape((n, n))
    ZtZ = F[o + 3 * nn:o + 4 * nn].reshape((n, n))
    Lr = F[o + 4 * nn:o + 5 * nn].reshape((n, n))
    Hr = F[o + 5 * nn:o + 6 * nn].reshape((n, n))
    Lsp = F[o + 6 * nn:o + 7 * nn].reshape((n, n))
    Y2 = F[o + 7 * nn:o + 8 * nn].reshape((n, n))
    o += 8 * nn
    ws = F[o:o + 15 * w].reshape((15, w))
    o += 15 * w
    lamr = F[o:o + m]
    o += m
    g = F[o:o + n]
    o += n
    H = F[o:o + nn].reshape((n, n))
    o += nn
    G = F[o:o + m * n].reshape((m, n))
    o += m * n
    h = F[o:o + m]
    b = F[o + m:o + 2 * m]
    o += 2 * m
    p = F[o:o + n]
    zt = F[o + n:o + 2 * n]
    lamW = F[o + 2 * n:o + 3 * n]
    o += 3 * n
    Xt = F[o:o + sz_x].reshape((N + 1, 4))
    Tc = F[o + sz_x:o + sz_x + 4 * N].reshape((N, 4))
    I = np.empty(4 * N + 3 * n + 2 * n + 1 + nz + m + n + 8 * N, dtype=np.int64)
    I[:4 * N] = -1
    I[4 * N:4 * N + 3 * n] = 0
    link = I[0:2 * N]
    fix = I[2 * N:4 * N]
    iv = I[4 * N:4 * N + 3 * n].reshape((n, 3))
    o = 4 * N + 3 * n
    lab = I[o:o + n]
    colptr = I[o + n:o + 2 * n + 1]
    o += 2 * n + 1
    zidx = I[o:o + nz]
    A = I[o + nz:o + nz + m]
    W = I[o + nz + m:o + nz + m + n]
    runs = I[o + nz + m + n:o + nz + m + n + 8 * N].reshape((2 * N, 4))
    Bf = np.zeros(2 * m, dtype=np.bool_)
    mv = Bf[0:m]
    inW = Bf[m:2 * m]
    qk = (link, fix, lab, colptr, zidx, zval, M, Hb, R, ZtZ, Lr, Hr, Lsp, ws, A, lamr, cv, Y2, Ls2, mv, iv,
          runs)
    return (S, lam, g, H, qk, G, h, b, p, zt, W, inW, lamW, Xt, Tc)


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
    (S, lam, g, H, qk, G, h, b, p, zt, W, inW, lamW, Xt, Tc) = wk
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
        J = derivatives(x0, z, xref, uprev, P, exact, X, Tc, S, lam, g, H)
        slacks(z, h, dt, b)
        dmax = 0.0
        for i in range(n):
            dmax = max(dmax, abs(H[i, i]))
        code, nW = qp_null_space(H, g, G, b, W, nW, qp_max_iter, p, lamW, inW, dmax, dt, qk)
        if code == 2:
            # the last resort: the Gauss-Newton Hessian at z (X, S, lam are still z's)
            hessian(z, X, Tc, S, lam, P, False, H)
            dmax = 0.0
            for i in range(n):
                dmax = max(dmax, abs(H[i, i]))
            code, nW = qp_null_space(H, g, G, b, W, nW, qp_max_iter, p, lamW, inW, dmax, dt, qk)
            if code == 2:
                return ST_QP, J, it
        # the QP's decrease, with p'Hc p = p'(gq - g) from the QP's model gradient gq = g + Hc p
        gq = qk[13][0]
        gp = 0.0
        gqp = 0.0
        for i in range(n):
            gp += g[i] * p[i]
            gqp += gq[i] * p[i]
        pred = -0.5 * (gp + gqp)
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
        if (code == 0 and alpha == 1.0 and it + 1 < max_iter and pred <= _EARLY_STOP_SKIP * (1.0 + J)
                and converged_after_step(x0, z, xref, uprev, P, Xt, Tc, Jt, h, G, W, nW, qk, lam, tol)):
            for k in range(N + 1):
                for i in range(4):
                    X[k, i] = Xt[k, i]
            return ST_OK, Jt, it + 1
        # the working set is kept: qp_null_space drops the rows no longer active at the new z
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
def solve_slot(bi, X0, Xref, Uprev, Uwarm, has_warm, Rprev, guesses, Pb, max_iter, qp_max_iter,
               Uout, Xout, cost, status, iters, starts):
    """Problem bi of a batch: checks, one or two starts (the second behind its gate and side
    rule; the cheaper converged result is kept), warm start and fallback. Rprev[bi] is the
    reference of the slot's previous solve (the gate's "new reference"). Touches only slot bi
    of every array, so slots can run on different threads.

    The solve works on private copies of the parameters and of slot bi's inputs and outputs:
    every call that passes an array updates the reference count of the memory it views, and
    two threads updating the count of the same shared array contend for its cache line."""
    N = Uwarm.shape[1]
    n = 2 * N
    ns = Pb.size
    B = np.empty(ns + 4 + 4 + 2 + 4 + 2 * N + 4 * n + (N + 1) * 4 + 2 * N)
    P = B[0:ns]
    x0 = B[ns:ns + 4]
    xref = B[ns + 4:ns + 8]
    uprev = B[ns + 8:ns + 10]
    xr = B[ns + 10:ns + 14]
    o = ns + 14
    vlo = B[o:o + N]
    vhi = B[o + N:o + 2 * N]
    o += 2 * N
    zlo = B[o:o + n]
    zhi = B[o + n:o + 2 * n]
    z = B[o + 2 * n:o + 3 * n]
    z2 = B[o + 3 * n:o + 4 * n]
    o += 4 * n
    X = B[o:o + (N + 1) * 4].reshape((N + 1, 4))
    warm = B[o + (N + 1) * 4:o + (N + 1) * 4 + 2 * N].reshape((N, 2))
    for i in range(ns):
        P[i] = Pb[i]
    for i in range(4):
        x0[i] = X0[bi, i]
        xref[i] = Xref[bi, i]
    for i in range(2):
        uprev[i] = Uprev[bi, i]
    for k in range(N):
        warm[k, 0] = Uwarm[bi, k, 0]
        warm[k, 1] = Uwarm[bi, k, 1]
    use = np.empty(guesses.size, dtype=np.bool_)
    for i in range(guesses.size):
        use[i] = guesses[i]
    st = prepare(x0, xref, uprev, P, xr, vlo, vhi, zlo, zhi)
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
        initial_guess(x0, xr, uprev, warm, has_warm[bi], use, P, vlo, vhi, zlo, zhi, z, X)
        wk = sqp_workspace(N, P)
        build_constraints(x0[2], vlo, vhi, zlo, zhi, P, wk[5], wk[6])
        st, J, it = sqp_ws(x0, xr, uprev, z, P, max_iter, qp_max_iter, vlo, vhi, zlo, zhi, X, wk, np.inf)
        # sqp_ws leaves X and J those of z when it succeeds; the second start overwrites X
        consistent = True
        if P[P_STEER_START] > 0.5 and max_iter > 0 and (
                st != ST_OK or P[P_STEER_GATE] < 0.5 or second_start_pays(z, X, xr, new_ref, zlo, zhi, P)):
            consistent = False
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
        if not consistent:
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
    for k in range(N + 1):
        for i in range(4):
            Xout[bi, k, i] = X[k, i]
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


@njit(cache=True)
def solve_one_kernel(x0, xref, uprev, Uwarm, has_warm, Rprev, guesses, P, max_iter, qp_max_iter, U, X, cost, info):
    """One problem (the batch of one of solve_batch_kernel) on 1-D inputs and the (N, 2) / (N+1, 4)
    outputs U, X; info = [status, iterations, starts]. The reshaping happens here, where it costs
    nothing, instead of in the caller's Python."""
    N = U.shape[0]
    solve_slot(0, x0.reshape((1, 4)), xref.reshape((1, 4)), uprev.reshape((1, 2)), Uwarm, has_warm, Rprev,
               guesses, P, max_iter, qp_max_iter, U.reshape((1, N, 2)), X.reshape((1, N + 1, 4)), cost,
               info[0:1], info[1:2], info[2:3])


@intrinsic
def _fetch_add(typingctx, arr, idx):
    """Atomically add 1 to the int64 arr[idx] and return its previous value."""
    sig = types.int64(arr, idx)

    def codegen(context, builder, signature, args):
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        ptr = builder.gep(ary.data, [args[1]])
        return builder.atomic_rmw("add", ptr, ir.Constant(ir.IntType(64), 1), "monotonic")
    return sig, codegen


@njit(cache=True, parallel=True)
def solve_batch_parallel(X0, Xref, Uprev, Uwarm, has_warm, Rprev, guesses, P, max_iter, qp_max_iter,
                         Uout, Xout, cost, status, iters, starts, nt):
    """As solve_batch_kernel, with the slots spread over nt workers on numba's threads (they
    share only read-only inputs); the same solve_slot runs, so the results are the serial ones.
    Each worker takes the next unsolved slot when it is done with one: solve times differ by a
    factor of twenty between slots, and a fixed split leaves one thread waiting."""
    nxt = np.zeros(8, dtype=np.int64)
    for t in prange(nt):
        while True:
            bi = _fetch_add(nxt, 0)
            if bi >= X0.shape[0]:
                break
            solve_slot(bi, X0, Xref, Uprev, Uwarm, has_warm, Rprev, guesses, P, max_iter, qp_max_iter,
                       Uout, Xout, cost, status, iters, starts)
