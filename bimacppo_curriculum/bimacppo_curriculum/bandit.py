"""Exp3.S-based bandit schedulers: the paper's BiMAB (Algorithm 1) and RD-ACPPO (ref. [41]).

Equations (11)-(17) of the paper, with its slips fixed (docs/curriculum.md has the long form):

* eq. (11): the arm softmax runs over the arms of cluster i (the text sums over N_ss^max);
* eq. (17): the arm weights accumulate the arm reward r_hat_ij (the text repeats r_hat_i);
* eq. (16): beta * W adds the same amount to every weight of a level. p ~ exp(w), so that
  term never changes a probability, but it makes the raw weights grow geometrically
  (factor 1 + K*beta per episode) until they overflow. We apply it as written and then
  re-centre each level so its mean stays at the initial weight. A common shift is
  invisible to the softmax, so the sampling law is exactly the paper's; the reported
  weights are the paper's weights minus a per-level constant, which keeps the differences
  between curves (all that Figs. 5-6 can mean) and stays bounded.
"""
from __future__ import annotations

import math

import numpy as np

from .base import Scheduler
from .config import BiMABConfig, RDConfig

# Relative size under which eq. (14)'s denominator k1*R_max - k0*R_min counts as zero.
# It is only reachable when k1 == k0 and every return so far had the same magnitude,
# i.e. when the history carries no information to normalise against.
_DEGENERATE_REL = 1e-12


class RewardRescaler:
    """Eq. (14)-(15): map an episode return to r_norm, using the history's |r| extremes.

    The formula is evaluated divided through by R_max, so returns of any finite size
    (1e300 included) never overflow: every intermediate lies in a range set by the
    constants alone, not by the return's scale.
    """

    def __init__(self, k0: float, k1: float, alpha_md: float):
        self.k0, self.k1, self.alpha_md = float(k0), float(k1), float(alpha_md)
        self.r_max: float | None = None  # max |r| so far (current episode included)
        self.r_min: float | None = None  # min |r| so far

    def observe(self, r: float) -> float:
        m = abs(float(r))
        self.r_max = m if self.r_max is None else max(self.r_max, m)
        self.r_min = m if self.r_min is None else min(self.r_min, m)
        return self.normalise(r)

    def normalise(self, r: float) -> float:
        """r_norm for return r against the current history (without adding r to it)."""
        if self.r_max is None or self.r_max == 0.0:
            return 0.0  # no magnitude seen yet: nothing to normalise against
        # r_md / R_max, eq. (15): negative returns are mirrored and scaled by alpha_md.
        a = (abs(r) / self.r_max) * (1.0 if r >= 0.0 else self.alpha_md)
        b = self.r_min / self.r_max
        den = self.k1 - self.k0 * b
        if den <= _DEGENERATE_REL * self.k1:
            return 0.0
        return 2.0 * (a - self.k0 * b) / den - 1.0

    def state(self) -> dict:
        return {"r_max": self.r_max, "r_min": self.r_min}

    def load(self, d: dict, where: str) -> None:
        vals = []
        for key in ("r_max", "r_min"):
            v = d.get(key, "missing")
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0):
                raise ValueError(f"{where}: key '{key}' must be null or a finite number >= 0, got {v!r}")
            vals.append(None if v is None else float(v))
        if (vals[0] is None) != (vals[1] is None) or (vals[0] is not None and vals[1] > vals[0]):
            raise ValueError(f"{where}: keys 'r_max'/'r_min' are inconsistent: {vals}")
        self.r_max, self.r_min = vals


def budget_scaling(c, total_episodes: int | None) -> tuple[int, float]:
    """(N_BiMAB, step-size factor) for a run of ``total_episodes`` (None: unknown budget).

    A fixed N_BiMAB lets a short run end before the bandit ever changes its sampling law (a
    1,000-episode run with N_BiMAB = 1000 samples uniformly throughout). With ``min_syncs``, any
    run syncs at least that often; with ``step_budget``, the step sizes shrink or grow with the
    budget so that alpha * T, the weight change a whole run can make, is that of a
    ``step_budget``-episode run at the configured alpha."""
    n, scale = c.sync_interval, 1.0
    if total_episodes is not None:
        if c.min_syncs is not None:
            n = max(1, min(n, total_episodes // c.min_syncs))
        if c.step_budget is not None:
            scale = c.step_budget / total_episodes
    return n, scale


class Exp3SLevel:
    """One level of the bandit: `rows` independent groups of `k` weights.

    The cluster level is one row of K_c = N_sv^max + 1 weights; the arm level is one row of
    three task weights per cluster. Holds both the sampling copy (BiMAB M) and the target
    copy (target BiMAB M-hat) of the weights.
    """

    def __init__(self, rows: int, k: int, w0: float, eta: float, alpha: float, beta: float):
        self.rows, self.k = rows, k
        self.w0, self.eta, self.alpha, self.beta = float(w0), float(eta), float(alpha), float(beta)
        self.w = np.full((rows, k), self.w0)       # sampling weights (M)
        self.tw = np.full((rows, k), self.w0)      # target weights (M-hat)
        self._p: np.ndarray | None = None          # cached sampling law

    def probs(self, target: bool = False) -> np.ndarray:
        """Eq. (11): (1 - eta) softmax(w) + eta / k, row by row; max-subtracted for stability.

        The sampling law only changes at a sync, so it is computed once per sync (returned
        read-only) instead of on every draw and update.
        """
        if not target and self._p is not None:
            return self._p
        w = self.tw if target else self.w
        e = np.exp(w - w.max(axis=1, keepdims=True))
        p = (1.0 - self.eta) * e / e.sum(axis=1, keepdims=True) + self.eta / self.k
        if not target:
            p.flags.writeable = False
            self._p = p
        return p

    def reinforce(self, row: int, col: int, r_hat: float) -> None:
        """Eq. (16) on the target weights; every other entry gets reward 0.

        Only the row holding the sampled entry is touched: in every other row eq. (16) adds
        beta*W to each weight and the re-centring takes exactly that back out, so skipping
        those rows is the same result without the rounding of a pointless add-and-subtract.
        """
        w = self.tw[row]                     # a view: edits land in self.tw
        big_w = w.sum()                      # W(t), before this update
        w[col] += self.alpha * r_hat
        w += self.beta * big_w               # same shift for the whole row
        w -= w.sum() / self.k - self.w0      # re-centre to mean w0 (softmax-invariant)

    def sync(self) -> None:
        """Eq. (17) / Algorithm 1 lines 11-13: copy the target into the sampling bandit."""
        self.w[...] = self.tw
        self._p = None

    def state(self) -> dict:
        return {"w": self.w.tolist(), "tw": self.tw.tolist()}

    def load(self, d: dict, where: str) -> None:
        arrs = []
        for key in ("w", "tw"):
            if key not in d:
                raise ValueError(f"{where}: missing key '{key}'")
            try:
                a = np.asarray(d[key], dtype=float)
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{where}: key '{key}' is not a numeric array ({exc})") from exc
            if a.shape != (self.rows, self.k) or not np.all(np.isfinite(a)):
                raise ValueError(f"{where}: key '{key}' must be a finite {self.rows}x{self.k} array, got shape {a.shape}")
            arrs.append(a)
        self.w, self.tw = arrs
        self._p = None


class _Exp3SScheduler(Scheduler):
    """Shared machinery: rescaling, the cluster level, the target/sync cycle, pending samples.

    Importance weighting (r_hat = r_norm / p) must use the probability the episode was drawn
    with. With several environments running at once, a sync can happen between a draw and
    its update, so each draw's probabilities are remembered (FIFO per scenario) and used when
    that scenario's return arrives; a return for a scenario this scheduler did not draw
    (e.g. chosen by someone else) falls back to the current sampling law.
    """

    def __init__(self, config=None, seed: int = 0, total_episodes: int | None = None):
        super().__init__(config, seed, total_episodes)
        c = self.config
        self.sync_interval, self.alpha_scale = budget_scaling(c, self.total_episodes)
        self.clusters = Exp3SLevel(1, self.n_clusters, c.initial_weight, c.eta, c.alpha_c * self.alpha_scale, c.beta_c)
        self.rescaler = RewardRescaler(c.k0, c.k1, c.alpha_md)
        self.pending: list[list] = []   # [i, j, p_i, p_ij] per draw not yet updated
        self.n_syncs = 0
        self.last_r_norm = 0.0

    # --- the law
    def arm_probabilities(self, target: bool = False) -> np.ndarray:
        raise NotImplementedError

    def probabilities(self):
        return self.clusters.probs()[0], self.arm_probabilities()

    def target_probabilities(self):
        """The law the next sync would install (the target bandit's)."""
        return self.clusters.probs(target=True)[0], self.arm_probabilities(target=True)

    # --- hooks
    def _on_sample(self, i, j, p_i, p_ij):
        if self.config.max_pending == 0:
            return
        self.pending.append([i, j, p_i, p_ij])
        if len(self.pending) > self.config.max_pending:
            del self.pending[0]

    def _pop_pending(self, i, j) -> tuple[float, float]:
        for n, (pi_, pj_, p_i, p_ij) in enumerate(self.pending):
            if pi_ == i and pj_ == j:
                del self.pending[n]
                return p_i, p_ij
        p_c = self.clusters.probs()[0]
        return float(p_c[i]), float(self.arm_probabilities()[i, j])

    def _update(self, i, j, r):
        p_i, p_ij = self._pop_pending(i, j)
        r_norm = self.rescaler.observe(r)
        self.last_r_norm = r_norm
        self.clusters.reinforce(0, i, r_norm / p_i)          # eq. (14) r_hat_i, eq. (16)
        self._reinforce_arm(i, j, r_norm / p_ij)            # eq. (14) r_hat_ij, eq. (16)
        if self.n_updates % self.sync_interval == 0:  # eq. (17), Algorithm 1 l. 11
            self.clusters.sync()
            self._sync_arms()
            self.n_syncs += 1

    def _reinforce_arm(self, i, j, r_hat):
        pass

    def _sync_arms(self):
        pass

    def _extra_log(self):
        out = {"syncs": float(self.n_syncs), "sync_interval": float(self.sync_interval),
               "last_r_norm": float(self.last_r_norm),
               # no history yet reads as 0: the rescaler then treats every return as r_norm = 0
               "r_max": 0.0 if self.rescaler.r_max is None else self.rescaler.r_max,
               "r_min": 0.0 if self.rescaler.r_min is None else self.rescaler.r_min}
        tp = self.clusters.probs(target=True)[0]
        for i in range(self.n_clusters):
            out[f"cluster_weight_{i}"] = float(self.clusters.w[0, i])
            out[f"target_cluster_weight_{i}"] = float(self.clusters.tw[0, i])
            out[f"target_cluster_prob_{i}"] = float(tp[i])
        return out

    def _extra_state(self):
        return {"clusters": self.clusters.state(), "rescaler": self.rescaler.state(),
                "pending": [list(p) for p in self.pending], "n_syncs": self.n_syncs,
                "last_r_norm": self.last_r_norm}

    def _load_extra_state(self, d):
        for key in ("clusters", "rescaler", "pending", "n_syncs", "last_r_norm"):
            if key not in d:
                raise ValueError(f"state: missing key '{key}'")
        n_syncs, last = d["n_syncs"], d["last_r_norm"]
        if isinstance(n_syncs, bool) or not isinstance(n_syncs, int) or n_syncs < 0:
            raise ValueError(f"state: key 'n_syncs' must be an integer >= 0, got {n_syncs!r}")
        if isinstance(last, bool) or not isinstance(last, (int, float)) or not math.isfinite(last):
            raise ValueError(f"state: key 'last_r_norm' must be a finite number, got {last!r}")
        if not isinstance(d["pending"], list):
            raise ValueError("state: key 'pending' must be a list")
        pending = []
        for p in d["pending"]:
            if (not isinstance(p, (list, tuple)) or len(p) != 4):
                raise ValueError(f"state: key 'pending' entries must be [i, j, p_i, p_ij], got {p!r}")
            i, j = self._check_index(p[0], p[1])
            pending.append([i, j, float(p[2]), float(p[3])])
        clusters = Exp3SLevel(1, self.n_clusters, self.clusters.w0, self.clusters.eta,
                              self.clusters.alpha, self.clusters.beta)
        clusters.load(d["clusters"], "state: key 'clusters'")
        rescaler = RewardRescaler(self.rescaler.k0, self.rescaler.k1, self.rescaler.alpha_md)
        rescaler.load(d["rescaler"], "state: key 'rescaler'")
        self._load_arm_state(d)  # validates, and assigns only when valid
        self.clusters, self.rescaler, self.pending = clusters, rescaler, pending
        self.n_syncs, self.last_r_norm = n_syncs, float(last)

    def _load_arm_state(self, d):
        pass


class BiMAB(_Exp3SScheduler):
    """The paper's Exp3.S bilevel bandit (Algorithm 1): clusters = N_sv, arms = task."""

    name = "bimab"
    config_cls = BiMABConfig

    def __init__(self, config=None, seed: int = 0, total_episodes: int | None = None):
        super().__init__(config, seed, total_episodes)
        c = self.config
        self.arms = Exp3SLevel(self.n_clusters, self.n_arms, c.initial_weight, c.eta,
                               c.alpha_a * self.alpha_scale, c.beta_a)

    def arm_probabilities(self, target=False):
        return self.arms.probs(target=target)

    def _reinforce_arm(self, i, j, r_hat):
        self.arms.reinforce(i, j, r_hat)

    def _sync_arms(self):
        self.arms.sync()

    def _extra_log(self):
        out = super()._extra_log()
        for i in range(self.n_clusters):
            for j in range(self.n_arms):
                out[f"arm_weight_{i}_{j}"] = float(self.arms.w[i, j])
                out[f"target_arm_weight_{i}_{j}"] = float(self.arms.tw[i, j])
        return out

    def _extra_state(self):
        return {**super()._extra_state(), "arms": self.arms.state()}

    def _load_arm_state(self, d):
        if "arms" not in d:
            raise ValueError("state: missing key 'arms'")
        arms = Exp3SLevel(self.n_clusters, self.n_arms, self.arms.w0, self.arms.eta, self.arms.alpha, self.arms.beta)
        arms.load(d["arms"], "state: key 'arms'")
        self.arms = arms  # last check of the load has passed: nothing after this can fail


class RDACPPO(_Exp3SScheduler):
    """RD-ACPPO (paper ref. [41]): the same Exp3.S machinery on N_sv only; the task is uniform."""

    name = "rd"
    config_cls = RDConfig

    def arm_probabilities(self, target=False):
        return np.full((self.n_clusters, self.n_arms), 1.0 / self.n_arms)
