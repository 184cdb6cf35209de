"""The NMPC of eq. (32)-(33) behind one interface, with two solver configurations.

* ``"ipopt"``: the paper's reference, CasADi ``nlpsol`` + IPOPT in single shooting
  (decision variables = the N inputs only).
* ``"fast"``: the same problem solved by the numba SQP of ``_kernels`` (exact Hessian, an
  active-set QP in the null space of its working set), reaching the same optimum in a small
  fraction of the time.

Both share the input checks, the heading unwrapping, the speed-bound tube, the rate bounds
(``_kernels.input_boxes`` and the steering-rate rows), the choice of the initial guess and
the fault handling, so that they solve the same problem and differ only in the optimiser.
A control step never raises on bad *values* (NaN/inf, solver failure): it returns the
safe fallback command with ``ok=False``; bad *shapes* are programming errors and raise
``ValueError``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from typing import List, Optional

import numpy as np

from . import _kernels as K
from .config import INITIAL_GUESSES, MPCConfig

STATUS_TEXT = {
    K.ST_OK: "ok",
    K.ST_MAX_ITER: "solver_failed: iteration limit reached",
    K.ST_LINESEARCH: "solver_failed: line search found no decrease",
    K.ST_QP: "solver_failed: QP subproblem failed",
    K.ST_INFEASIBLE: "infeasible: speed bounds unreachable from the current speed",
    K.ST_NONFINITE_STATE: "bad_input: non-finite state x0",
    K.ST_NONFINITE_REF: "bad_input: non-finite reference x_ref",
    K.ST_NONFINITE_UPREV: "bad_input: non-finite previous input u_prev",
    K.ST_NONFINITE_RESULT: "solver_failed: non-finite solution",
    K.ST_ABANDONED: "solver_failed: second start abandoned",
}

SOLVERS = ("fast", "ipopt")


@dataclass(slots=True)
class MPCResult:
    """One control step. ``u`` is always finite and within the input bounds."""

    u: np.ndarray            # (2,) [a, delta] to apply now
    U: np.ndarray            # (N, 2) planned inputs
    X: np.ndarray            # (N+1, 4) predicted states [x, y, v, psi] (NaN if x0 was not finite)
    cost: float              # eq. (32) objective at U (NaN on failure)
    status: str              # "ok" or the reason of the fallback
    ok: bool
    solve_time_s: float
    iterations: int = 0
    starts: int = 1          # SQP starts run (fast solver: 2 when the second start ran; 0 on bad input)


@dataclass
class MPCBatchResult:
    """B independent control steps (one per batch slot)."""

    u: np.ndarray            # (B, 2)
    U: np.ndarray            # (B, N, 2)
    X: np.ndarray            # (B, N+1, 4)
    cost: np.ndarray         # (B,)
    ok: np.ndarray           # (B,) bool
    status: List[str]
    solve_time_s: float      # the whole batch
    iterations: np.ndarray   # (B,)
    starts: Optional[np.ndarray] = None   # (B,) SQP starts run by the fast solver


def pack_params(cfg: MPCConfig) -> np.ndarray:
    """The config as the flat float vector the numba kernels read."""
    P = np.zeros(K.P_SIZE)
    P[K.P_L] = cfg.wheelbase
    P[K.P_DT] = cfg.dt
    P[K.P_AMIN], P[K.P_AMAX] = cfg.a_min, cfg.a_max
    P[K.P_DMIN], P[K.P_DMAX] = cfg.delta_min, cfg.delta_max
    P[K.P_VMIN], P[K.P_VMAX] = cfg.v_min, cfg.v_max
    P[K.P_QX:K.P_QX + 4] = cfg.q_x
    P[K.P_QU:K.P_QU + 2] = cfg.q_u
    P[K.P_QDU:K.P_QDU + 2] = cfg.q_du
    P[K.P_BRAKE] = cfg.brake_decel
    P[K.P_RELAX] = 1.0 if cfg.relax_infeasible_speed_bounds else 0.0
    P[K.P_TOL] = cfg.fast.tol
    P[K.P_EXACT] = 1.0 if cfg.fast.hessian == "exact" else 0.0
    P[K.P_STEER_START] = 1.0 if cfg.fast.steer_bound_start else 0.0
    P[K.P_STEER_GATE] = 1.0 if cfg.fast.steer_bound_gate else 0.0
    P[K.P_STEER_RATE] = cfg.steer_rate_max if cfg.steer_rate_max is not None else 0.0
    P[K.P_JERK] = cfg.jerk_max if cfg.jerk_max is not None else 0.0
    P[K.P_CUT] = cfg.fast.second_start_cut if cfg.fast.second_start_cut is not None else 0.0
    P[K.P_OTHER_SIDE] = 1.0 if cfg.fast.steer_bound_other_side else 0.0
    return P


def _as_array(name: str, value, shape) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: not numeric ({exc})") from None
    if arr.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {arr.shape}")
    return np.ascontiguousarray(arr)


def _vector(name: str, value, size: int) -> np.ndarray:
    """_as_array for a 1-D vector, without copies or checks beyond the type test when value
    already is a contiguous float64 array of that size (the common case in a control loop)."""
    if type(value) is np.ndarray and value.dtype == np.float64 and value.shape == (size,) \
            and value.flags.c_contiguous:
        return value
    return _as_array(name, value, (size,))


def _python_fallback(cfg: MPCConfig, x0: np.ndarray, u_prev: np.ndarray) -> np.ndarray:
    """The fallback command without numba, for when the kernel itself raised."""
    a = max(cfg.a_min, cfg.brake_decel)
    v0 = float(x0[2]) if x0.size > 2 else float("nan")
    if np.isfinite(v0) and v0 >= cfg.v_min:
        a = min(max(a, (cfg.v_min - v0) / cfg.dt), 0.0)
    d = float(u_prev[1]) if np.isfinite(u_prev[1]) else 0.0
    return np.array([a, min(max(d, cfg.delta_min), cfg.delta_max)])


class MPCController:
    """Shared front end: shapes, warm-start slots, timing and the error barrier."""

    solver_name = ""

    def __init__(self, cfg: MPCConfig):
        if not isinstance(cfg, MPCConfig):
            raise ValueError(f"cfg: expected MPCConfig, got {type(cfg).__name__}")
        self.cfg = cfg
        self.N = cfg.horizon
        self.P = pack_params(cfg)
        self.guesses = np.array([g in cfg.fast.initial_guesses for g in INITIAL_GUESSES], dtype=np.bool_)
        self.reset()

    # ---------------------------------------------------------------- public API
    def reset(self, slots=None) -> None:
        """Forget warm starts (call at the start of an episode): every one, or only those of
        ``solve_batch`` slots ``slots`` (one episode of a batch restarting while the others run)."""
        if slots is not None:
            idx = np.asarray(slots, dtype=np.int64).reshape(-1)
            n = self._hasB.shape[0]
            if n == 0:
                return                # no batch solved yet: nothing is warm
            if idx.size and (idx.min() < 0 or idx.max() >= n):
                raise ValueError(f"slots {idx.tolist()} outside the batch of {n}")
            self._hasB[idx] = False
            return
        self._warm1 = np.zeros((1, self.N, 2))
        self._has1 = np.zeros(1, dtype=np.bool_)
        self._ref1 = np.zeros((1, 4))          # the reference of each slot's previous solve
        self._warmB = np.zeros((0, self.N, 2))
        self._hasB = np.zeros(0, dtype=np.bool_)
        self._refB = np.zeros((0, 4))

    def solve(self, x0, x_ref, u_prev) -> MPCResult:
        x0 = _as_array("x0", x0, (4,))
        x_ref = _as_array("x_ref", x_ref, (4,))
        u_prev = _as_array("u_prev", u_prev, (2,))
        t0 = time.perf_counter()
        b = self._run(x0[None], x_ref[None], u_prev[None], self._warm1, self._has1, self._ref1)
        dt = time.perf_counter() - t0
        return MPCResult(u=b.u[0], U=b.U[0], X=b.X[0], cost=float(b.cost[0]), status=b.status[0],
                         ok=bool(b.ok[0]), solve_time_s=dt, iterations=int(b.iterations[0]),
                         starts=int(b.starts[0]))

    def solve_batch(self, X0, Xref, Uprev) -> MPCBatchResult:
        """B independent problems; slot i keeps its own warm start while B stays the same."""
        X0 = np.asarray(X0, dtype=float)
        if X0.ndim != 2:
            raise ValueError(f"X0: expected shape (B, 4), got {X0.shape}")
        B = X0.shape[0]
        X0 = _as_array("X0", X0, (B, 4))
        Xref = _as_array("Xref", Xref, (B, 4))
        Uprev = _as_array("Uprev", Uprev, (B, 2))
        if self._warmB.shape[0] != B:
            self._warmB = np.zeros((B, self.N, 2))
            self._hasB = np.zeros(B, dtype=np.bool_)
            self._refB = np.zeros((B, 4))
        t0 = time.perf_counter()
        out = self._run(X0, Xref, Uprev, self._warmB, self._hasB, self._refB)
        out.solve_time_s = time.perf_counter() - t0
        return out

    # ---------------------------------------------------------------- internals
    def _run(self, X0, Xref, Uprev, warm, has_warm, ref_prev) -> MPCBatchResult:
        B = X0.shape[0]
        U = np.zeros((B, self.N, 2))
        X = np.zeros((B, self.N + 1, 4))
        cost = np.full(B, np.nan)
        status = np.zeros(B, dtype=np.int64)
        iters = np.zeros(B, dtype=np.int64)
        self._starts = starts = np.ones(B, dtype=np.int64)
        texts: Optional[List[str]] = None
        try:
            texts = self._solve_all(X0, Xref, Uprev, warm, has_warm, ref_prev, U, X, cost, status, iters)
        except Exception as exc:  # the error barrier: a control step never raises
            msg = f"solver_error: {type(exc).__name__}: {exc}"
            texts = [msg] * B
            has_warm[:] = False
            cost[:] = np.nan
            for i in range(B):
                u = _python_fallback(self.cfg, X0[i], Uprev[i])
                U[i] = u
                X[i] = np.nan
            status[:] = -1
        if texts is None:
            texts = [STATUS_TEXT[int(s)] for s in status]
        ok = np.array([t == "ok" for t in texts], dtype=bool)
        # last line of defence: whatever happened, the command is finite and in bounds
        lo = np.array([self.cfg.a_min, self.cfg.delta_min])
        hi = np.array([self.cfg.a_max, self.cfg.delta_max])
        bad = ~np.all(np.isfinite(U[:, 0, :]), axis=1)
        for i in np.nonzero(bad)[0]:
            U[i] = _python_fallback(self.cfg, X0[i], Uprev[i])
            ok[i] = False
            texts[i] = STATUS_TEXT[K.ST_NONFINITE_RESULT]
        U = np.clip(U, lo, hi)
        return MPCBatchResult(u=U[:, 0, :].copy(), U=U, X=X, cost=cost, ok=ok, status=texts,
                              solve_time_s=0.0, iterations=iters, starts=starts)

    def _solve_all(self, X0, Xref, Uprev, warm, has_warm, ref_prev, U, X, cost, status, iters):
        raise NotImplementedError


class FastController(MPCController):
    """numba SQP; the whole batch runs in one compiled call, over several threads when it is large."""

    solver_name = "fast"

    def __init__(self, cfg: MPCConfig):
        super().__init__(cfg)
        self._lo = (cfg.a_min, cfg.delta_min)
        self._hi = (cfg.a_max, cfg.delta_max)
        self._cost1 = np.empty(1)
        self._info1 = np.empty(3, dtype=np.int64)     # status, iterations, starts of solve()
        self._max_iter, self._qp_max_iter = cfg.fast.max_iter, cfg.fast.qp_max_iter
        self.set_threads(cfg.fast.threads)

    def set_threads(self, threads: int) -> None:
        """Threads for a batch of at least ``fast.parallel_min_batch`` problems (0: numba's default, one per core)."""
        import numba

        if not isinstance(threads, (int, np.integer)) or isinstance(threads, bool) or threads < 0:
            raise ValueError(f"threads: expected an integer >= 0, got {threads!r}")
        self.threads = min(int(threads), numba.config.NUMBA_NUM_THREADS) or numba.config.NUMBA_NUM_THREADS

    def solve(self, x0, x_ref, u_prev) -> MPCResult:
        # The kernel of solve_batch for one problem, without the batch bookkeeping: at ~0.05 ms
        # per solve the Python around the kernel is a sizeable share of the time.
        x0 = _vector("x0", x0, 4)
        x_ref = _vector("x_ref", x_ref, 4)
        u_prev = _vector("u_prev", u_prev, 2)
        t0 = time.perf_counter()
        N = self.N
        U = np.empty((N, 2))
        X = np.empty((N + 1, 4))
        info = self._info1
        try:
            K.solve_one_kernel(x0, x_ref, u_prev, self._warm1, self._has1, self._ref1, self.guesses, self.P,
                               self._max_iter, self._qp_max_iter, U, X, self._cost1, info)
        except Exception:  # the error barrier of _run turns it into the fallback
            return self._single(self._run(x0[None], x_ref[None], u_prev[None], self._warm1, self._has1,
                                          self._ref1), t0)
        a, d = U.item(0), U.item(1)
        if not (self._lo[0] <= a <= self._hi[0] and self._lo[1] <= d <= self._hi[1]):   # also catches NaN
            return self._single(self._run(x0[None], x_ref[None], u_prev[None], self._warm1, self._has1,
                                          self._ref1), t0)
        st = info.item(0)
        return MPCResult(u=U[0].copy(), U=U, X=X, cost=self._cost1.item(0), status=STATUS_TEXT[st],
                         ok=st == K.ST_OK, solve_time_s=time.perf_counter() - t0,
                         iterations=info.item(1), starts=info.item(2))

    @staticmethod
    def _single(b: MPCBatchResult, t0: float) -> MPCResult:
        return MPCResult(u=b.u[0], U=b.U[0], X=b.X[0], cost=float(b.cost[0]), status=b.status[0],
                         ok=bool(b.ok[0]), solve_time_s=time.perf_counter() - t0, iterations=int(b.iterations[0]),
                         starts=int(b.starts[0]))

    def _solve_all(self, X0, Xref, Uprev, warm, has_warm, ref_prev, U, X, cost, status, iters):
        f = self.cfg.fast
        args = (X0, Xref, Uprev, warm, has_warm, ref_prev, self.guesses, self.P, f.max_iter, f.qp_max_iter,
                U, X, cost, status, iters, self._starts)
        if X0.shape[0] < f.parallel_min_batch or self.threads == 1:
            K.solve_batch_kernel(*args)
            return None
        import numba

        before = numba.get_num_threads()
        numba.set_num_threads(self.threads)
        try:
            K.solve_batch_parallel(*args, self.threads)
        finally:
            numba.set_num_threads(before)
        return None


class IpoptController(MPCController):
    """CasADi nlpsol + IPOPT, single shooting: the configuration of the paper (§IV-A)."""

    solver_name = "ipopt"

    def __init__(self, cfg: MPCConfig):
        super().__init__(cfg)
        self._solver = self._build()

    def _build(self):
        import casadi as ca

        cfg, N = self.cfg, self.N
        Z = ca.SX.sym("z", 2 * N)          # [a_0, delta_0, a_1, delta_1, ...]
        par = ca.SX.sym("p", 10)           # x0 (4), x_ref (4, heading unwrapped), u_prev (2)
        x = par[0:4]
        ref = par[4:8]
        u_last = par[8:10]
        qx = ca.DM(cfg.q_x)
        qu = ca.DM(cfg.q_u)
        qdu = ca.DM(cfg.q_du)
        J = ca.dot(qx, (x - ref) ** 2)
        speeds = []
        # the steering rate rows of the fast solver (delta_k - delta_{k-1}, k >= 1); the first
        # move's rate bounds are the per-problem boxes lbx/ubx of _kernels.input_boxes
        rates = [Z[2 * k + 1] - Z[2 * k - 1] for k in range(1, N)] if cfg.steer_rate_max is not None else []
        for k in range(N):
            u = Z[2 * k:2 * k + 2]
            du = u - u_last
            J += ca.dot(qu, u ** 2) + ca.dot(qdu, du ** 2)
            v, psi, a, d = x[2], x[3], u[0], u[1]
            f = ca.vertcat(v * ca.cos(psi + d), v * ca.sin(psi + d), a, 2 * v / cfg.wheelbase * ca.sin(d))
            x = x + cfg.dt * f
            J += ca.dot(qx, (x - ref) ** 2)
            speeds.append(x[2])
            u_last = u
        nlp = {"x": Z, "p": par, "f": J, "g": ca.vertcat(*speeds, *rates)}
        opts = {
            "print_time": False,
            "ipopt.print_level": cfg.ipopt.print_level,
            "ipopt.max_iter": cfg.ipopt.max_iter,
            "ipopt.tol": cfg.ipopt.tol,
            "ipopt.sb": "yes",
        }
        step = cfg.steer_rate_max * cfg.dt if rates else 0.0
        self._rate_lo = np.full(len(rates), -step)
        self._rate_hi = np.full(len(rates), step)
        return ca.nlpsol("bimacppo_mpc_ipopt", "ipopt", nlp, opts)

    def _solve_all(self, X0, Xref, Uprev, warm, has_warm, ref_prev, U, X, cost, status, iters):
        N = self.N
        P = self.P
        xr = np.empty(4)
        vlo = np.empty(N)
        vhi = np.empty(N)
        zlo = np.empty(2 * N)
        zhi = np.empty(2 * N)
        z = np.empty(2 * N)
        texts = []
        for i in range(X0.shape[0]):
            st = K.prepare(X0[i], Xref[i], Uprev[i], P, xr, vlo, vhi, zlo, zhi)
            text = STATUS_TEXT[st]
            if st == K.ST_OK:
                K.initial_guess(X0[i], xr, Uprev[i], warm[i], has_warm[i], self.guesses, P, vlo, vhi, zlo, zhi,
                                z, X[i])
                try:
                    sol = self._solver(x0=z, p=np.concatenate([X0[i], xr, Uprev[i]]), lbx=zlo, ubx=zhi,
                                       lbg=np.concatenate([vlo, self._rate_lo]),
                                       ubg=np.concatenate([vhi, self._rate_hi]))
                    stats = self._solver.stats()
                    iters[i] = int(stats.get("iter_count", 0))
                    if stats.get("success", False):
                        z = np.array(sol["x"], dtype=float).ravel()
                    else:
                        st = K.ST_MAX_ITER if stats.get("return_status") == "Maximum_Iterations_Exceeded" \
                            else K.ST_QP
                        text = f"solver_failed: ipopt {stats.get('return_status')}"
                except Exception as exc:  # IPOPT/CasADi errors become a fallback, not a crash
                    st = K.ST_QP
                    text = f"solver_error: {type(exc).__name__}: {exc}"
            if st == K.ST_OK:
                # IPOPT relaxes bounds by ~1e-8 internally; the projection makes them exact
                K.project(z, X0[i, 2], vlo, vhi, zlo, zhi, P)
                K.rollout(X0[i], z, P, X[i])
                J = K.cost_of(X[i], z, xr, Uprev[i], P)
                if np.isfinite(J) and np.all(np.isfinite(z)):
                    U[i] = z.reshape(N, 2)
                    warm[i] = U[i]
                    has_warm[i] = True
                    cost[i] = J
                else:
                    st = K.ST_NONFINITE_RESULT
                    text = STATUS_TEXT[st]
            if st != K.ST_OK:
                u = np.empty(2)
                K.fallback(X0[i], Uprev[i], P, u)
                U[i] = u
                has_warm[i] = False
                cost[i] = np.nan
                if np.all(np.isfinite(X0[i])):
                    K.rollout(X0[i], np.tile(u, N), P, X[i])
                else:
                    X[i] = np.nan
            status[i] = st
            texts.append(text)
        return texts


def make_controller(cfg: Optional[MPCConfig] = None, solver: str = "fast") -> MPCController:
    """The controller for ``solver`` in ("fast", "ipopt"); ``cfg`` defaults to the packaged YAML."""
    cfg = MPCConfig.load() if cfg is None else cfg
    if solver == "fast":
        return FastController(cfg)
    if solver == "ipopt":
        return IpoptController(cfg)
    raise ValueError(f"solver: expected one of {SOLVERS}, got {solver!r}")
