"""Statistics over seeds and episodes (pure functions: tested on synthetic data)."""
from __future__ import annotations

import contextlib
import warnings
from typing import Mapping

import numpy as np


def aggregate_cells(tables: list[Mapping]) -> dict[tuple[int, int], dict]:
    """Per cell, mean and sample standard deviation (ddof=1; NaN for one seed) of S/C/TO
    across the given evaluation tables; a cell counts only the tables that have it."""
    keys = sorted({k for t in tables for k in t})
    out = {}
    for key in keys:
        a = np.array([t[key][:3] for t in tables if key in t], float)
        std = a.std(axis=0, ddof=1) if len(a) > 1 else np.full(3, np.nan)
        out[key] = {"n": len(a), "mean": a.mean(axis=0), "std": std}
    return out


def rolling_rate(recs: list[dict], window: int) -> tuple[np.ndarray, np.ndarray]:
    """(episode, success rate over the last ``window`` episodes), only where a full window exists."""
    from ..report import rolling_success

    x, y = rolling_success(recs, window)
    keep = x >= window
    return x[keep], y[keep]


def episodes_to_fraction(recs: list[dict], window: int, fraction: float) -> tuple[int | None, float]:
    """(first episode whose rolling success reaches ``fraction`` x the final one, final rate).
    Final = the rolling rate at the last episode. None when the run has no full window or its
    final rate is 0 (nothing to reach)."""
    x, y = rolling_rate(recs, window)
    if not len(x):
        return None, float("nan")
    final = float(y[-1])
    if final <= 0.0:
        return None, final
    hit = np.nonzero(y >= fraction * final - 1e-12)[0]
    return int(x[hit[0]]), final


def mean_std_curve(histories: list[list[dict]], window: int):
    """Rolling success of several seeds on their common episode range: (x, mean, std)."""
    curves = [rolling_rate(h, window) for h in histories]
    curves = [c for c in curves if len(c[0])]
    if not curves:
        return None
    hi = min(int(c[0][-1]) for c in curves)
    x = np.arange(window, hi + 1, dtype=float)
    ys = np.array([np.interp(x, cx, cy) for cx, cy in curves])
    return x, ys.mean(axis=0), ys.std(axis=0, ddof=1) if len(ys) > 1 else None


def mean_counts(logs: list[Mapping]) -> dict[str, float]:
    """Table I over seeds: mean of each count_i / count_i_j of the schedulers' final logs."""
    keys = sorted({k for lg in logs for k in lg if k.startswith("count_")})
    return {k: float(np.mean([lg.get(k, 0.0) for lg in logs])) for k in keys}


@contextlib.contextmanager
def _seeded_bootstrap(seed: int):
    """rliable's StratifiedBootstrap draws its resamples from NumPy's global generator
    (``np.random.choice`` in ``update_indices``), not from the ``random_state`` it is given. So
    the global generator is seeded here and restored afterwards: the intervals are reproducible
    and the caller's random stream is untouched. arch's warning that ``random_state`` is
    deprecated is silenced."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="random_state is deprecated", category=FutureWarning)
            yield np.random.RandomState(seed)
    finally:
        np.random.set_state(state)


def success_matrix(tables: list[Mapping], cells: list) -> np.ndarray:
    """Runs x cells matrix of success (%) for rliable: one row per evaluation table (a training
    seed), one column per evaluation cell (task, N_sv). Every table must have every cell."""
    missing = [(i, c) for i, t in enumerate(tables) for c in cells if c not in t]
    if missing:
        raise ValueError(f"evaluation tables lack cells {missing[:3]}: every run needs every cell")
    return np.array([[float(t[c][0]) for c in cells] for t in tables], float).reshape(len(tables), len(cells))


def iqm_intervals(scores: Mapping[str, np.ndarray], reps: int = 2000, seed: int = 0) -> dict[str, dict]:
    """Per method: the interquartile mean and the mean of its (runs x cells) scores, each with
    rliable's stratified bootstrap 95 % interval (runs resampled within each cell).

    The IQM (the mean of the middle 50 % of all run x cell scores) is the aggregate rliable
    recommends for few runs: robust to one outlier seed, yet far less noisy than the median."""
    from rliable import library as rly
    from rliable import metrics

    if reps < 1:
        raise ValueError(f"reps must be >= 1, got {reps}")

    def both(x):
        return np.array([metrics.aggregate_iqm(x), metrics.aggregate_mean(x)])

    with _seeded_bootstrap(seed) as rs:
        point, ci = rly.get_interval_estimates({k: np.asarray(v, float) for k, v in scores.items()}, both,
                                               reps=reps, random_state=rs)
    return {k: {"runs": int(np.asarray(scores[k]).shape[0]), "iqm": float(point[k][0]), "mean": float(point[k][1]),
                "iqm_ci": (float(ci[k][0, 0]), float(ci[k][1, 0])),
                "mean_ci": (float(ci[k][0, 1]), float(ci[k][1, 1]))} for k in scores}


def improvement_probability(x: np.ndarray, y: np.ndarray, reps: int = 2000, seed: int = 0) -> dict:
    """P(X > Y): the probability that a run of X beats a run of Y on a random cell (rliable's
    probability of improvement, Mann-Whitney per cell, averaged over cells), with its stratified
    bootstrap 95 % interval. 0.5 means no difference."""
    from rliable import library as rly
    from rliable import metrics

    x, y = np.asarray(x, float), np.asarray(y, float)
    if x.shape[1:] != y.shape[1:]:
        raise ValueError(f"X and Y need the same cells, got {x.shape[1:]} and {y.shape[1:]}")
    with _seeded_bootstrap(seed) as rs:
        point, ci = rly.get_interval_estimates({"xy": (x, y)}, metrics.probability_of_improvement, reps=reps,
                                               random_state=rs)
    return {"p": float(np.squeeze(point["xy"])), "ci": (float(ci["xy"][0].squeeze()), float(ci["xy"][1].squeeze()))}
